"""Calibration workflows over recorded data: lens distortion, hand-eye, video-kinematics time offset.
OpenCV's YAML (cv2.FileStorage) is the exchange format."""
