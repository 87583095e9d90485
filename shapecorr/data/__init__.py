"""Data layer: mesh I/O and validation, the Shape record, the shape cache, datasets."""
