"""Optimizer plugins.  :mod:`.dense_ba` registers two schedules of one dense bundle adjustment: ``online_ba`` (the
PV-SLAM paper's: a sliding-window BA as each keyframe arrives) and ``offline_ba`` (DROID-SLAM's: a small local BA
per keyframe and a global BA over every keyframe at the end)."""
