"""The conditions stage: the scene mesh warped into ERP condition frames and masks along the trajectory."""
