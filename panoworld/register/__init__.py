"""Registration of several panoramas of one home: given poses validated, or ERP features + depth-backed 3D-3D RANSAC."""
