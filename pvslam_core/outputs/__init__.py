"""Run outputs: trajectory files (TUM/KITTI), PLY point clouds, panoptic PNGs, metrics JSON and plots.

Every writer here is atomic (temp file in the same folder + ``os.replace``) so that a run stopped by an error
or Ctrl-C leaves valid files holding what had been flushed.
"""
