"""File helpers: atomic writes, trajectory formats, reading text files, and the records and
naming rules of a results folder that its writer (SLAM) and its reader (eval) share."""
