"""File output helpers: atomic writes, trajectory formats."""
