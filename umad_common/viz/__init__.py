"""Pictures and reports of an evaluation: curves, overlay grids, tables."""
