"""Bundle-adjustment optimizer plugins: ``online_ba`` (sliding-window BA on every keyframe, the PV-SLAM paper's)
and ``offline_ba`` (DROID-SLAM style local BA plus a global BA at the end); shared code in :mod:`.common`."""
