"""Surface from inlier points: alpha-shape mesh (VTK via PyVista) and off-screen rendering."""
