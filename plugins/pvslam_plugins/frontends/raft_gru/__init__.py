"""``raft_gru``: the learned visual-odometry frontend of DROID-SLAM / PVO, in plain torch (CPU and CUDA).

Registered as the frontend ``raft_gru`` (``frontend.plugin = "raft_gru"``; entry point in pyproject.toml), with a
trainer (``pvslam train frontend --plugin raft_gru``).

Modules
-------
* :mod:`.encoders`    - image normalisation and the feature / context encoders (``fnet``, ``cnet``), stride 8.
* :mod:`.corr`        - correlation pyramid and lookup: a stored full volume (:class:`CorrVolume`) and a
  memory-light on-the-fly path (:class:`OnTheFlyCorr`) that gives the same numbers.
* :mod:`.update`      - the update operator (ConvGRU with global context, heads, graph aggregation), DROID's
  ``UpdateModule`` and PVO's ``DynamicUpdateModule`` as two variants of one class.
* :mod:`.upsample`    - convex upsampling (disparity / flow) and PVO's bilinear ``upsample_inter``.
* :mod:`.net`         - :class:`RaftGruNet`, the ``DroidNet``-like container (upstream parameter names).
* :mod:`.checkpoint`  - loading droid.pth, PVO checkpoints and this project's own checkpoints.
* :mod:`.config`      - the frontend's configuration (profiles ``droid`` / ``fast``).
* :mod:`.edge_step`   - motion input, PVO's dynamic mask, eq. 4 weights (shared by frontend and trainer).
* :mod:`.frontend`    - :class:`RaftGruFrontend`: DROID's motion filter, per-edge GRU state by stable ids,
  update -> BA rounds, learned damping, upsampled depth.
* :mod:`.frontend_state` - what the frontend stores per keyframe / per edge, stage timings, :func:`load_network`.
* :mod:`.train_ba`, :mod:`.train_data`, :mod:`.losses`, :mod:`.train` - training (DROID's losses through a
  differentiable dense BA on clips of the built-in synthetic generator).

Every tensor is reproduced against the upstream modules' own numbers (``shared/fixtures`` sections A and B).
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl

from .checkpoint import CheckpointError, LoadedCheckpoint, load_checkpoint, load_model, save_checkpoint
from .corr import CorrVolume, OnTheFlyCorr, coords_grid, make_corr
from .encoders import frames_to_images, normalize_images
from .net import Features, RaftGruNet, droid_motion, pvo_motion
from .update import UpdateModule, UpdateOutput
from .upsample import cvx_upsample, upsample_disp, upsample_flow, upsample_inter

__all__ = [
    "CheckpointError",
    "CorrVolume",
    "Features",
    "LoadedCheckpoint",
    "OnTheFlyCorr",
    "RaftGruNet",
    "UpdateOutput",
    "UpdateModule",
    "coords_grid",
    "cvx_upsample",
    "droid_motion",
    "frames_to_images",
    "load_checkpoint",
    "load_model",
    "make_corr",
    "normalize_images",
    "pvo_motion",
    "save_checkpoint",
    "upsample_disp",
    "upsample_flow",
    "upsample_inter",
]


@hookimpl
def register_frontends(register):
    from pvslam_core.training import Trainer

    from .config import RaftGruConfig
    from .frontend import make_frontend
    from .train import TrainConfig, run

    register(
        "raft_gru",
        make_frontend,
        RaftGruConfig,
        description="DROID-SLAM / PVO learned frontend: RAFT encoders, correlation pyramid, ConvGRU update with "
        "per-edge state, update -> dense BA rounds, learned damping, PVO dynamic mask (eq. 4/6)",
        ba_downsample=8,  # the network's feature stride: the BA resolution is not fitted to small images
        trainer=Trainer(TrainConfig, run, description="DROID's losses (pose after BA, induced flow, residual; "
                        "PVO's mask loss) through a differentiable dense BA on built-in synthetic clips"),
    )
