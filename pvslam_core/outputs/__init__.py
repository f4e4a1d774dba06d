"""Run outputs: trajectory files (TUM/KITTI), PLY point clouds, panoptic PNGs, keyframe depth, metrics JSON, plots
and exports.

Every writer here is atomic (temp file in the same folder + ``os.replace``, with the mode the umask gives) so
that a run stopped by an error or Ctrl-C leaves valid files holding what had been flushed.

Where each file of a run directory comes from:

* ``trajectory.txt``, ``keyframes.txt``, ``groundtruth.txt`` -- :mod:`.trajectory_io` (TUM, T_wc);
* ``groundtruth_loops.json`` -- the dataset's revisit pairs, so ``pvslam eval`` needs no dataset;
* ``loops.json`` -- :mod:`.loops_io`;
* ``panoptic/NNNNNN.png`` + ``panoptic/segments.json`` (COCO panoptic format) -- :mod:`.panoptic_png`;
* ``cloud_rgb.ply``, ``cloud_panoptic.ply`` (cleaned: :mod:`.cloud`) -- :mod:`.ply`;
* ``keyframes/NNNNNN_depth.npy`` + ``keyframes/keyframes.json`` (poses, intrinsics) -- :mod:`.keyframes_io`;
* ``metrics.json`` -- :mod:`.metrics`; ``plots/`` -- :mod:`.plots`;
* ``export/colmap|nerfstudio|tum-aligned/`` (``pvslam export``) -- :mod:`.export`, :mod:`.colmap`,
  :mod:`.nerfstudio`; the formats are the table of :mod:`.formats` (a new format: its writer module plus one line
  there).
"""
