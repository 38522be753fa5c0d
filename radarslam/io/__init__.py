"""File helpers: atomic writes, trajectory formats, reading text files."""
