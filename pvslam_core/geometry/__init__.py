"""Geometry for pvslam: batched SE3/Sim3 (:mod:`.lie`), projective operations (:mod:`.projective`),
dense bundle adjustment (:mod:`.ba`) and the Sim(3) pose graph (:mod:`.pose_graph`)."""
