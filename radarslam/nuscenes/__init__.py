"""Reading (and, for the simulator, writing) the nuScenes radar layout without the devkit."""
