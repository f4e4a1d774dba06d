"""DeiT loop-closure benchmark: CPU cost of the descriptors, and offline place recognition on held-out seeds.

    python bench/bench_deit.py speed [--threads 2] [--batch 8] [--reps 3] [--frame 240x320]
    python bench/bench_deit.py retrieval [--seeds 301 302] [--weights-dir DIR] [--verify]
    python bench/bench_deit.py validate [--seeds 201 202] [--weights-dir DIR]

``speed``: ms per keyframe of ``DeitDescriptor.features`` (preprocessing: resize + normalise; forward; token
selection) for DeiT-base and DeiT-base-distilled at full size (86 M parameters, random weights: the cost does not
depend on the values) and for the small architecture trained here (embed 192, depth 4, 3 heads), at 224 (the
upstream input: 224x224 centre crop, and the full frame on the same 196-patch budget) and at 112 (the trained
models' input, 96x128 full frame for 320x240 frames).  Median over ``reps`` batches after one warm-up batch:
wall time, and process CPU time (summed over threads, less sensitive to other load on a shared machine).

``retrieval``: the protocol of :mod:`pvslam_plugins.loops.deit.place_eval` (every 3rd frame a keyframe, temporal
exclusion of 20 keyframes and 10 s, candidates more than 60 degrees apart skipped as by the loop policy, top-1
correct within 5 frames of a ground-truth revisit pair) on generated
sequences of ``driving_loop`` and ``indoor_handheld``: the classical global descriptor and the DeiT checkpoints,
each at its own calibrated threshold (from its checkpoint; classical: its config default) and at the threshold
that would give precision 1.00 on these very seeds (an oracle, for the gap only).  ``--verify`` adds, for each
descriptor, the rows with the geometric verification the detectors share (``verify = true``: the best of at most 3
candidates above the threshold that passes ORB + essential-matrix RANSAC on the 320x240 frames, with the
verification defaults), as ``place_eval.verified_top_one`` counts it; the "P=1.00 threshold" column is then blank.

``validate``: the evidence for the detector's ``verify`` default, on the *validation* seeds (201 202: the ones the
thresholds were calibrated on, never the report seeds).  (1) Cross-validation of the threshold calibration: the
threshold calibrated (best wrong top-1 + 10 %) on one seed's sequences, evaluated on the other seed's, retrieval-only
vs verified; (2) margin: pooled over the seeds, retrieval-only vs verified at the calibrated threshold and 0.02,
0.05, 0.1 below it (how many wrong candidates each lets through when the score scale shifts a little).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from pvslam_plugins.loops.deit.config import DeitDescriptorConfig
from pvslam_plugins.loops.deit.descriptor import DeitDescriptor
from pvslam_plugins.loops.deit.vit import ViTConfig, build_vit, deit_base_distilled_patch16_224, deit_base_patch16_224

#: (label, resize mode, input_size)
CASES = [
    ("224x224 crop", "center_crop", 224),
    ("full frame, 224 budget", "full_frame", 224),
    ("full frame, 112 budget", "full_frame", 112),
]


def _small(distilled: bool):
    return build_vit(ViTConfig(img_size=(96, 128), embed_dim=192, depth=4, num_heads=3, num_classes=0,
                               distilled=distilled))


def speed(args) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    h, w = (int(v) for v in args.frame.split("x"))
    frames = torch.randint(0, 256, (args.batch, 3, h, w), dtype=torch.uint8)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {args.batch}, frames {h}x{w} uint8, "
          f"median of {args.reps}")
    print("| model | variant | input | patches | ms/keyframe wall | ms/keyframe CPU (all threads) |")
    print("|---|---|---|---|---|---|")
    models = [("DeiT-base (86 M)", "base", deit_base_patch16_224),
              ("DeiT-base (86 M)", "distilled", deit_base_distilled_patch16_224),
              ("small (192x4)", "base", lambda: _small(False)),
              ("small (192x4)", "distilled", lambda: _small(True))]
    for arch, variant, ctor in models:
        model = ctor().eval()
        for label, mode, size in CASES:
            desc = DeitDescriptor(model, DeitDescriptorConfig(resize=mode, input_size=size, batch_size=args.batch))
            ih, iw = desc.input_size(h, w)
            desc.features(frames)  # warm-up (also fills the pos_embed cache for this grid)
            times, cpu = [], []
            for _ in range(args.reps):
                t0, c0 = time.perf_counter(), time.process_time()
                desc.features(frames)
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            ms = 1000.0 * statistics.median(times) / args.batch
            cpu_ms = 1000.0 * statistics.median(cpu) / args.batch
            print(f"| {arch} | {variant} | {label}: {ih}x{iw} | {(ih // 16) * (iw // 16)} | {ms:.1f} | {cpu_ms:.1f} |",
                  flush=True)


def retrieval(args) -> None:
    import torch.nn.functional as F

    from pvslam_plugins.datasets.synthetic.generator import generate
    from pvslam_plugins.loops.classical.config import ClassicalLoopConfig
    from pvslam_plugins.loops.deit.checkpoint import load_checkpoint
    from pvslam_plugins.loops.deit.descriptor import WEIGHTS_DIR, select_tokens
    from pvslam_plugins.loops.deit.place_eval import calibrate, metrics_at, top_one, verified_top_one
    from pvslam_plugins.loops.deit.train import prefix_tokens
    from pvslam_plugins.loops.deit.train_data import PlaceSequence

    torch.set_num_threads(args.threads)
    wdir = Path(args.weights_dir) if args.weights_dir else WEIGHTS_DIR
    cks = {p.stem: load_checkpoint(p) for p in sorted(wdir.glob("*.pt"))}
    print(f"seeds {args.seeds}; checkpoints: {', '.join(cks) or 'none'} ({wdir})")
    print("| scenario | descriptor | threshold | precision | recall | recall@1 | revisit queries | best wrong | "
          "P=1.00 threshold on these seeds (recall there) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for sc in args.scenarios:
        roots = [Path(generate(sc, seed=s, progress=False)) for s in args.seeds]
        size = next(iter(cks.values())).descriptor.get("input_size", 112) if cks else 112
        seqs = [PlaceSequence(r, size if isinstance(size, int) else tuple(size), hard_k=1) for r in roots]
        descs = {"classical": [s.teacher[::3] for s in seqs]}  # unit descriptors [K, d] per sequence
        thresholds = {"classical": ClassicalLoopConfig().threshold}
        for name, ck in cks.items():
            d = ck.descriptor
            descs[name] = []
            for s in seqs:
                t = prefix_tokens(ck.model, s.frames[::3])
                f = select_tokens(t, d.get("token", "cls"), t.shape[1])
                if ck.pca is not None and d.get("pca") == "fixed":
                    f = ck.pca.transform(f)
                descs[name].append(F.normalize(f, dim=1))
            thresholds[name] = float(d.get("threshold", 0.8))
        rows = {name: ([top_one(d, s.labels.pos, s.timestamps, axes=s.axes) for d, s in zip(ds, seqs)],
                       thresholds[name]) for name, ds in descs.items()}
        for name, (res, thr) in rows.items():
            m, o = metrics_at(res, thr), calibrate(res)
            print(f"| {sc} | {name} | {thr:.3f} | {m['precision']:.2f} | {m['recall']:.2f} | {m['recall_at_1']:.2f} | "
                  f"{m['revisit_queries']} | {o['best_wrong']:.3f} | {o['threshold']:.3f} ({o['recall']:.2f}) |",
                  flush=True)
        if not args.verify:
            continue
        verifiers = [_keyframe_verifier(r) for r in roots]
        for name, (res, thr) in rows.items():
            vres = [verified_top_one(d, s.labels.pos, s.timestamps, thr, lambda i, j, v=v: bool(v.verify(i, j).accepted),
                                     axes=s.axes) for d, s, v in zip(descs[name], seqs, verifiers)]
            m = metrics_at(vres, thr)
            wrong = torch.cat([r.score[torch.isfinite(r.score) & ~r.correct] for r in vres])
            bw = f"{float(wrong.max()):.3f}" if len(wrong) else "-"
            print(f"| {sc} | {name} + verify | {thr:.3f} | {m['precision']:.2f} | {m['recall']:.2f} | - | "
                  f"{m['revisit_queries']} | {bw} | |", flush=True)


def _sequences(args):
    """{(scenario, seed): (PlaceSequence, KeyframeVerifier, {descriptor name: unit descriptors [K, d]})}, the
    checkpoints {variant: LoadedCheckpoint}."""
    import torch.nn.functional as F

    from pvslam_plugins.datasets.synthetic.generator import generate
    from pvslam_plugins.loops.deit.checkpoint import load_checkpoint
    from pvslam_plugins.loops.deit.descriptor import WEIGHTS_DIR, select_tokens
    from pvslam_plugins.loops.deit.train import prefix_tokens
    from pvslam_plugins.loops.deit.train_data import PlaceSequence

    torch.set_num_threads(args.threads)
    wdir = Path(args.weights_dir) if args.weights_dir else WEIGHTS_DIR
    cks = {v: load_checkpoint(wdir / f"deit_synth_{v}.pt") for v in ("base", "distilled")}
    data = {}
    for sc in args.scenarios:
        for sd in args.seeds:
            root = Path(generate(sc, seed=sd, progress=False))
            seq = PlaceSequence(root, tuple(cks["base"].descriptor.get("input_size", (96, 128))), hard_k=1)
            descs = {"classical": seq.teacher[::3]}
            for name, ck in cks.items():
                t = prefix_tokens(ck.model, seq.frames[::3])
                f = select_tokens(t, ck.descriptor.get("token", "cls"), t.shape[1])
                if ck.pca is not None and ck.descriptor.get("pca") == "fixed":
                    f = ck.pca.transform(f)
                descs[name] = F.normalize(f, dim=1)
            data[(sc, sd)] = (seq, _keyframe_verifier(root), descs)
    return data, cks


def validate(args) -> None:
    from pvslam_plugins.loops.classical.config import ClassicalLoopConfig
    from pvslam_plugins.loops.deit.place_eval import calibrate, metrics_at, top_one, verified_top_one

    data, cks = _sequences(args)
    cache: dict = {}

    def check(v):  # verification results are reused across thresholds (ORB + RANSAC is the cost here)
        def f(i, j):
            if (id(v), i, j) not in cache:
                cache[(id(v), i, j)] = bool(v.verify(i, j).accepted)
            return cache[(id(v), i, j)]
        return f

    def plain(name, sc, sd):
        s, _, d = data[(sc, sd)]
        return top_one(d[name], s.labels.pos, s.timestamps, axes=s.axes)

    def both(name, sc, sd, thr):
        s, v, d = data[(sc, sd)]
        return plain(name, sc, sd), verified_top_one(d[name], s.labels.pos, s.timestamps, thr, check(v), axes=s.axes)

    def fmt(m):
        return f"{m['precision']:.2f} | {m['recall']:.2f} | {m['false']} / {m['detections']}"

    print("| descriptor | calibrated on | threshold | evaluated on | scenario | retrieval-only P | R | false / det "
          "| verified P | R | false / det |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for name in ("base", "distilled"):
        for cal in args.seeds:
            thr = calibrate([plain(name, sc, cal) for sc in args.scenarios])["threshold"]
            for ev in (s for s in args.seeds if s != cal):
                for sc in args.scenarios:
                    r, rv = both(name, sc, ev, thr)
                    print(f"| {name} | {cal} | {thr:.3f} | {ev} | {sc} | {fmt(metrics_at([r], thr))} | "
                          f"{fmt(metrics_at([rv], thr))} |", flush=True)
    print("\n| descriptor | threshold | scenario | retrieval-only P | R | false / det | verified P | R | false / det |"
          "\n|---|---|---|---|---|---|---|---|---|")
    for name in ("classical", "base", "distilled"):
        t0 = ClassicalLoopConfig().threshold if name == "classical" else float(cks[name].descriptor["threshold"])
        for thr in (t0, t0 - 0.02, t0 - 0.05, t0 - 0.1):
            for sc in args.scenarios:
                rs, rvs = zip(*(both(name, sc, sd, thr) for sd in args.seeds))
                print(f"| {name} | {thr:.3f} | {sc} | {fmt(metrics_at(rs, thr))} | {fmt(metrics_at(rvs, thr))} |",
                      flush=True)


def _keyframe_verifier(root: Path, stride: int = 3):
    """A :class:`KeyframeVerifier` (the detectors' verification defaults) holding every ``stride``-th frame of a
    generated sequence at full resolution, keyed by frame index."""
    import json

    import cv2

    from pvslam_core.types import Intrinsics
    from pvslam_plugins.loops.deit.config import DeitLoopConfig
    from pvslam_plugins.loops.verification import KeyframeVerifier

    cam = json.loads((root / "meta.json").read_text())["camera"]
    K = Intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"], cam["width"], cam["height"])
    names = [ln.split()[1] for ln in (root / "rgb.txt").read_text().splitlines() if ln.strip() and ln[0] != "#"]
    v = KeyframeVerifier(DeitLoopConfig(weights=None))
    for i in range(0, len(names), stride):
        v.add(i, cv2.imread(str(root / names[i]), cv2.IMREAD_GRAYSCALE), K)
    return v


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sp = sub.add_parser("speed", help="ms per keyframe")
    sp.add_argument("--threads", type=int, default=2)
    sp.add_argument("--batch", type=int, default=8)
    sp.add_argument("--reps", type=int, default=3)
    sp.add_argument("--frame", default="240x320", help="frame HxW (KITTI: 376x1241)")
    rp = sub.add_parser("retrieval", help="offline place recognition on held-out seeds")
    rp.add_argument("--seeds", type=int, nargs="+", default=[301, 302])
    rp.add_argument("--scenarios", nargs="+", default=["driving_loop", "indoor_handheld"])
    rp.add_argument("--weights-dir", default=None, help="folder of project checkpoints (default: the shipped ones)")
    rp.add_argument("--threads", type=int, default=2)
    rp.add_argument("--verify", action="store_true", help="also the rows with geometric verification")
    vp = sub.add_parser("validate", help="the verify default: cross-validated thresholds and margins, validation seeds")
    vp.add_argument("--seeds", type=int, nargs="+", default=[201, 202])
    vp.add_argument("--scenarios", nargs="+", default=["driving_loop", "indoor_handheld"])
    vp.add_argument("--weights-dir", default=None, help="folder of project checkpoints (default: the shipped ones)")
    vp.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    {"speed": speed, "retrieval": retrieval, "validate": validate}[args.cmd](args)


if __name__ == "__main__":
    main()
