"""The depth stage: ERP metric depth, its cleaning, completion and outliers, the capture rig's detection and removal."""
