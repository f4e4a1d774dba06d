"""Training pieces against brute-force references (labels, axes, losses, augmentation, the validation protocol),
and a tiny ``pvslam train loop --plugin deit`` run that checkpoints, resumes and exports a loadable model."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pvslam_plugins.loops.deit.place_eval import calibrate, metrics_at, top_one
from pvslam_plugins.loops.deit.train import distill_loss, margin_loss, supcon
from pvslam_plugins.loops.deit.train_data import Augment, pair_labels, quat_to_axis


def test_axes_and_pair_labels_brute_force():
    rng = np.random.default_rng(0)
    q = Rotation.random(12, random_state=1).as_quat()  # x, y, z, w
    axes = quat_to_axis(q)
    assert np.allclose(axes, Rotation.from_quat(q).apply([0.0, 0.0, 1.0]), atol=1e-12)
    # a few near-duplicates so that every label occurs
    centres = rng.uniform(0, 6, (12, 3))
    centres[1], axes[1] = centres[0] + 0.1, axes[0]
    centres[2], axes[2] = centres[0] + 1.0, -axes[0]
    c, a = torch.from_numpy(centres), torch.from_numpy(axes)
    lab = pair_labels(c, a, radius=1.0, max_angle_deg=20.0, neg_factor=3.0, neg_angle_deg=60.0)
    for i in range(12):
        for j in range(12):
            d = np.linalg.norm(centres[i] - centres[j])
            ang = math.degrees(math.acos(np.clip(axes[i] @ axes[j], -1, 1)))
            pos = d <= 1.0 and ang <= 20.0
            neg = (d > 3.0 or ang > 60.0) and not pos
            assert bool(lab.pos[i, j]) == pos and bool(lab.neg[i, j]) == neg, (i, j)
    assert lab.pos[0, 1] and lab.neg[0, 2]


def test_supcon_matches_a_loop_reference():
    g = torch.Generator().manual_seed(0)
    z = torch.nn.functional.normalize(torch.randn(7, 5, generator=g), dim=1)
    pos = torch.rand(7, 7, generator=g) > 0.6
    pos = pos | pos.T
    neg = ~pos & (torch.rand(7, 7, generator=g) > 0.3)
    neg = neg & neg.T
    tau = 0.2
    terms = []
    for a in range(7):
        P = [p for p in range(7) if p != a and pos[a, p]]
        V = [k for k in range(7) if k != a and (pos[a, k] or neg[a, k])]
        if not P or not any(neg[a, k] for k in range(7) if k != a):
            continue
        den = sum(math.exp(float(z[a] @ z[k]) / tau) for k in V)
        terms.append(-sum(float(z[a] @ z[p]) / tau - math.log(den) for p in P) / len(P))
    assert float(supcon(z, pos, neg, tau)) == pytest.approx(sum(terms) / len(terms), rel=1e-5)
    # the margin term is zero when positives are above and negatives below their margins
    m = margin_loss(z, pos, neg, m_pos=-1.0, m_neg=1.0)
    assert float(m) == 0.0


def test_distill_loss_is_finite_and_zero_at_the_teacher():
    g = torch.Generator().manual_seed(1)
    t = torch.nn.functional.normalize(torch.randn(6, 4, generator=g), dim=1)
    z = t.clone().requires_grad_(True)
    loss = distill_loss(z, t, tau=0.1, t_tau=0.1)  # same structure, same temperature
    assert loss.item() == pytest.approx(0.0, abs=1e-6)
    loss = distill_loss(torch.nn.functional.normalize(torch.randn(6, 4, generator=g), dim=1).requires_grad_(True),
                        t, tau=0.1, t_tau=0.05)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() > 0


def test_augment_range_determinism_and_identity():
    x = torch.randint(0, 256, (3, 3, 32, 48), dtype=torch.uint8)
    a = Augment()
    y1 = a(x, torch.Generator().manual_seed(3))
    y2 = a(x, torch.Generator().manual_seed(3))
    assert y1.shape == (3, 3, 32, 48) and torch.equal(y1, y2) and y1.min() >= 0 and y1.max() <= 1
    ident = Augment(gain=(1.0, 1.0), gamma=(1.0, 1.0), colour=0.0, noise=0.0, crop_min=1.0)
    assert torch.allclose(ident(x), x.float() / 255, atol=1e-5)


def test_top_one_and_calibration_brute_force():
    # 30 frames; frames 24..29 revisit frames 0..5 (positives); descriptors: a revisit matches its original,
    # everything else is random
    g = torch.Generator().manual_seed(2)
    n = 30
    desc = torch.nn.functional.normalize(torch.randn(n, 16, generator=g), dim=1)
    desc[24:] = torch.nn.functional.normalize(desc[:6] + 0.1 * torch.randn(6, 16, generator=g), dim=1)
    pos = torch.eye(n, dtype=torch.bool)
    for r in range(6):
        pos[24 + r, r] = pos[r, 24 + r] = True
    ts = torch.arange(n, dtype=torch.float64)
    res = top_one(desc[::2], pos, ts, stride=2, exclude_recent=3, min_time_gap=0.0, tolerance=0)
    kf = list(range(0, n, 2))
    for qi, q in enumerate(kf):
        elig = [j for pj, j in enumerate(kf) if pj <= qi - 4]
        if not elig:
            assert res.match[qi] == -1
            continue
        best = max(elig, key=lambda j: float(desc[q] @ desc[j]))
        assert int(res.match[qi]) == best
        assert bool(res.correct[qi]) == bool(pos[q, best])
        assert bool(res.revisit[qi]) == any(pos[q, j] for j in elig)
    assert res.revisit.sum() == 3 and res.correct.sum() == 3  # 24, 26, 28 find 0, 2, 4
    cal = calibrate([res])
    wrong = res.score[torch.isfinite(res.score) & ~res.correct]
    assert cal["best_wrong"] == pytest.approx(float(wrong.max()))
    assert cal["precision"] == 1.0 and cal["recall"] == 1.0
    m = metrics_at([res], -1.0)
    assert m["detections"] == int(torch.isfinite(res.score).sum()) and m["recall_at_1"] == 1.0


@pytest.mark.slow
def test_tiny_training_run_resumes_and_exports(tmp_path):
    from pvslam_core.training import train
    from pvslam_plugins.loops.deit.detector import DeitLoopDetector
    from pvslam_plugins.loops.deit.config import DeitLoopConfig

    sets = ["scenarios=['driving_loop']", "train_seeds=[0]", "val_seeds=[1]", "num_frames=40", "embed_dim=32",
            "depth=1", "num_heads=2", "input_size=32", "anchors=4", "hard=2", "steps=4", "checkpoint_every=2",
            "val_every=2", "exclude_recent=2", "min_time_gap=0.0", "progress=false", "threads=1",
            f"data_cache='{(tmp_path / 'cache').as_posix()}'", "variant='distilled'"]
    out, summary = train("loop", "deit", None, sets, tmp_path / "run")
    with open(out / "train_log.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4] and all(math.isfinite(float(r["loss"])) for r in rows)
    assert all(float(r["distill"]) > 0 for r in rows)  # the distillation term is active
    assert (out / "curves.png").is_file() and (out / "state.pt").is_file()
    assert summary["steps"] == 4 and summary["chosen"]["token"] in ("cls", "dist", "mean")
    _, again = train("loop", "deit", None, [v if v != "steps=4" else "steps=6" for v in sets], out, resume=True)
    with open(out / "train_log.csv") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [1, 2, 3, 4, 5, 6]
    assert again["steps"] == 6
    saved = json.loads((out / "summary.json").read_text())
    assert saved["chosen"] == again["chosen"]
    # the exported model is a detector's weights
    det = DeitLoopDetector(DeitLoopConfig(weights=str(out / "model.pt"), variant="distilled"))
    assert det.trained and det.config.threshold == pytest.approx(again["chosen"]["threshold"])
