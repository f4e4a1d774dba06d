"""DeiT loop-closure benchmark: CPU cost of the descriptors, and offline place recognition on held-out seeds.

    python bench/bench_deit.py speed [--threads 2] [--batch 8] [--reps 3] [--frame 240x320]
    python bench/bench_deit.py retrieval [--seeds 301 302] [--weights-dir DIR]

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
that would give precision 1.00 on these very seeds (an oracle, for the gap only).
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
    from pvslam_plugins.loops.deit.place_eval import calibrate, metrics_at, top_one
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
        rows = {"classical": ([top_one(s.teacher[::3], s.labels.pos, s.timestamps, axes=s.axes) for s in seqs],
                              ClassicalLoopConfig().threshold)}
        for name, ck in cks.items():
            d = ck.descriptor
            res = []
            for s in seqs:
                t = prefix_tokens(ck.model, s.frames[::3])
                f = select_tokens(t, d.get("token", "cls"), t.shape[1])
                if ck.pca is not None and d.get("pca") == "fixed":
                    f = ck.pca.transform(f)
                res.append(top_one(F.normalize(f, dim=1), s.labels.pos, s.timestamps, axes=s.axes))
            rows[name] = (res, float(d.get("threshold", 0.8)))
        for name, (res, thr) in rows.items():
            m, o = metrics_at(res, thr), calibrate(res)
            print(f"| {sc} | {name} | {thr:.3f} | {m['precision']:.2f} | {m['recall']:.2f} | {m['recall_at_1']:.2f} | "
                  f"{m['revisit_queries']} | {o['best_wrong']:.3f} | {o['threshold']:.3f} ({o['recall']:.2f}) |",
                  flush=True)


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
    args = ap.parse_args(argv)
    speed(args) if args.cmd == "speed" else retrieval(args)


if __name__ == "__main__":
    main()
