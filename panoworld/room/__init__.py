"""The room beyond what is seen: floor and ceiling planes, wall colours, layout columns, shadows, back sides."""
