"""Geometry shared by the stages: the ERP mesh, ray casting, cube views, similarity alignment, depth resizing."""
