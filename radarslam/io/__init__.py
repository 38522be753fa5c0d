"""File helpers: atomic writes, trajectory formats, reading text files, and the results folder
that its writers (``radarslam run``, ``radarslam odometry``) and its reader (eval) share."""
