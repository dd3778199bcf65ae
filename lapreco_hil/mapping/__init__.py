"""Structure from tracks and robot poses: triangulation, keyframes, robust bundle adjustment (GTSAM)."""
