"""The mesh stage: a home's panoramas fused into one mesh (one panorama's ERP mesh is panoworld.geometry.erp_mesh)."""
