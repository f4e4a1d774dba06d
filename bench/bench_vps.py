"""Benchmark of the VPS heads: ``fusion`` vs ``warp_iou`` vs no VPS, on the same non-oracle segmenter
(the shipped ``panoptic_fpn``), on held-out seeds of the generator's scenarios with moving vehicles.

    python bench/bench_vps.py                                         # report seeds 200 201 202, 80 frames each
    python bench/bench_vps.py --seeds 101 --frames 60 --out runs/bench/results_vps_tune.json   # the tuning seed
    python bench/bench_vps.py --timing 15                             # CPU ms per update, one frame pair
    python bench/bench_vps.py --domain heldout --out runs/bench/results_vps_heldout.json   # looks never trained on

One pipeline run per (scenario, seed) (synthetic reader, panoptic_fpn segmenter, the default VO, no loop closure):
its VPS head is a recorder that hands every frame's segmentation and motion cue to the three heads side by side,
so all three see identical inputs.  Per head: PQ and VPQ (VPSNet's k = 0, 5, 10, 15) against the generator's
labels, and ms per frame of its ``update`` (wall and thread CPU time; the machine is shared, CPU time is the
figure to read).  ``none`` is the segmenter's own per-frame ids (no temporal consistency).  The fusion head's
weights were trained on seeds 10-14 and, in the generator's training look, 15-19, and validated on seed 100
(``pvslam train vps --plugin fusion``); the segmenter was trained on seeds 1-8 and, restyled, 11-18.  Results:
JSON (``--out``, default runs/bench/results_vps.json, with the commit of the measured code:
:mod:`bench.provenance`) and a printed table.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from itertools import islice
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402
HEADS = ("none", "warp_iou", "fusion")
SCENARIOS = ("moving_vehicles", "busy_street")  # the scenes with moving vehicles: ids must stay consistent there
FRAMES = 80  # frames per sequence


class _Recorder:
    """A VPS head that runs the three compared heads on the same inputs and keeps their outputs and costs."""

    def __init__(self, fusion_cfg: dict) -> None:
        from pvslam_plugins.vps.fusion.config import FusionConfig
        from pvslam_plugins.vps.fusion.head import FusionHead
        from pvslam_plugins.vps.warp_iou.head import WarpIoUHead

        self.heads = {"warp_iou": WarpIoUHead(), "fusion": FusionHead(FusionConfig(**fusion_cfg))}
        self.states: dict = {k: None for k in self.heads}
        self.preds: dict = {k: [] for k in HEADS}
        self.gts: list = []
        self.wall: dict = {k: [] for k in self.heads}
        self.cpu: dict = {k: [] for k in self.heads}
        self.fused_frames = 0

    def update(self, prev, frame, seg, cue):
        from pvslam_core.interfaces import VPSState
        from pvslam_core.types import PanopticSegmentation

        _ = seg.ids, seg.features  # resolve a deferred segmentation outside the timers
        self.preds["none"].append((seg.ids.to(torch.int32), {s.id: s.category_id for s in seg.segments}))
        self.gts.append(frame.gt_panoptic)
        for name, head in self.heads.items():
            t0, c0 = time.perf_counter(), time.thread_time()
            self.states[name] = head.update(self.states[name], frame, seg, cue)
            self.wall[name].append(time.perf_counter() - t0)
            self.cpu[name].append(time.thread_time() - c0)
            p = self.states[name].panoptic
            self.preds[name].append((p.ids.to(torch.int32), {s.id: s.category_id for s in p.segments}))
        self.fused_frames += int(self.heads["fusion"].last_fused is not None)
        return VPSState(frame.index, PanopticSegmentation(seg.ids, list(seg.segments), seg.features), frame.image)


def _plugin(fusion_cfg: dict):
    """A registry module that registers the recorder as VPS plugin ``bench_recorder``."""
    from pvslam_core.config_base import PluginConfig
    from pvslam_core.registry import hookimpl

    class _Cfg(PluginConfig):
        pass

    class _Module:
        recorder: Optional[_Recorder] = None

        @hookimpl
        def register_vps_heads(self, register):  # type: ignore[no-untyped-def]
            def make(config, context=None):
                _Module.recorder = _Recorder(fusion_cfg)
                return _Module.recorder

            register("bench_recorder", make, _Cfg, description="bench_vps.py: fusion / warp_iou / none side by side")

    return _Module()


def run_sequence(scenario: str, seed: int, frames: int, fusion_cfg: dict, domain: Optional[str] = None) -> dict:
    from pvslam_core.config import load_config
    from pvslam_core.evaluation.panoptic import pq, vpq
    from pvslam_core.pipeline import Pipeline
    from pvslam_core.registry import build_registry

    import pvslam_plugins.vps.fusion as fusion_plugin

    mod = _plugin(fusion_cfg)
    reg = build_registry()
    extra = (mod,) if ("vps", "fusion") in reg.plugins else (mod, fusion_plugin)
    reg = build_registry(extra_modules=extra)
    cfg = load_config(str(ROOT / "configs" / "moving_vehicles.toml"), overrides=[
        f'dataset.scenario="{scenario}"', f"dataset.seed={seed}", f"dataset.num_frames={frames}",
        "dataset.progress=false", 'segmenter.plugin="panoptic_fpn"', 'vps.plugin="bench_recorder"',
        'loop.plugin="none"', "run.progress=false", "run.threads=1",
        *([f'dataset.domain="{domain}"'] if domain else [])], registry=reg)
    pipe = Pipeline(cfg, None, reg)
    pipe.start()
    t0 = time.perf_counter()
    for frame in islice(pipe.dataset, frames):
        pipe.step(frame)
    rec = mod.recorder
    cats = pipe.categories()
    out = {"scenario": scenario, "seed": seed, "domain": domain, "frames": len(rec.gts),
           "fused_frames": rec.fused_frames,
           "seconds": time.perf_counter() - t0, "load": os.getloadavg()[0], "heads": {}}
    for name in HEADS:
        p = pq(rec.preds[name], rec.gts, cats)
        v = vpq(rec.preds[name], rec.gts, cats)
        row = {"pq": p["pq"], "pq_things": p["things"]["pq"], "pq_stuff": p["stuff"]["pq"], "vpq": v["vpq"],
               "vpq_things": v["vpq_things"], "vpq_stuff": v["vpq_stuff"],
               "vpq_per_k": {k: v["per_k"][k]["pq"] for k in v["per_k"]}}
        if name in rec.wall:
            w, c = rec.wall[name][1:], rec.cpu[name][1:]  # the first frame has nothing to warp
            row.update(ms_wall_median=1e3 * statistics.median(w), ms_cpu_median=1e3 * statistics.median(c),
                       ms_cpu_mean=1e3 * statistics.mean(c))
        out["heads"][name] = row
    return out


def section_timing(reps: int, fusion_cfg: dict) -> dict:
    """CPU ms of one update of each head on a fixed pair of busy_street frames (seed 101, frames 40 -> 41; a DIS
    flow reduced to 1/8 and the generator's depth as the motion cue), median of ``reps`` calls, and the split of
    the fusion head's cost."""
    import cv2
    import numpy as np

    from pvslam_core.interfaces import MotionCue
    from pvslam_core.types import Frame, Intrinsics
    from pvslam_plugins.datasets.synthetic.render import render
    from pvslam_plugins.datasets.synthetic.scenarios import build
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenter, PanopticFPNSegmenterConfig
    from pvslam_plugins.vps.fusion.config import FusionConfig
    from pvslam_plugins.vps.fusion.feature_warp import warp_pyramid
    from pvslam_plugins.vps.fusion.head import FusionHead, motion_field
    from pvslam_plugins.vps.warp_iou.head import WarpIoUHead
    from pvslam_plugins.vps.warp_iou.warp import dis_flow

    sc = build("busy_street", width=320, height=240, seed=101)
    rs = [render(sc.scene, i, sc.poses[i], sc.camera) for i in (40, 41)]
    cam = sc.camera
    frames = [Frame(k, 0.1 * k, torch.from_numpy(r.rgb.transpose(2, 0, 1).copy()),
                    Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, 320, 240)) for k, r in enumerate(rs)]
    seg = PanopticFPNSegmenter(PanopticFPNSegmenterConfig(frames="all"))
    segs = [seg.segment(f) for f in frames]
    f = dis_flow(frames[0].image, frames[1].image, "ultrafast", 320)
    f = cv2.resize(np.ascontiguousarray(f.transpose(1, 2, 0)), (40, 30), interpolation=cv2.INTER_AREA) / 8.0
    cue = MotionCue(flow=torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))),
                    depth_prev=torch.from_numpy(np.asarray(rs[0].depth, np.float32)[4::8, 4::8].copy()))

    def cpu_ms(fn) -> float:
        fn()
        ts = []
        for _ in range(reps):
            c = time.thread_time()
            fn()
            ts.append(1e3 * (time.thread_time() - c))
        return statistics.median(ts)

    out = {}
    for name, head in (("warp_iou", WarpIoUHead()), ("fusion", FusionHead(FusionConfig(**fusion_cfg))),
                       ("fusion_proposals50", FusionHead(FusionConfig(**{**fusion_cfg, "proposals": 50})))):
        st = head.update(None, frames[0], segs[0], MotionCue())
        out[name] = cpu_ms(lambda: head.update(st, frames[1], segs[1], cue))
        if name == "fusion":
            m = head.model
            out["fusion.fuse (warp + conv + decode)"] = cpu_ms(lambda: head.fuse(st, frames[1], segs[1], cue))
            pyr = m.pyramid_for(segs[1].features.maps, (240, 320))
            with torch.no_grad():
                out["fusion.decode"] = cpu_ms(lambda: m.decode(pyr))
                flow, depth = motion_field(st.panoptic, cue, (240, 320), True)
                out["fusion.warp_pyramid"] = cpu_ms(lambda: warp_pyramid(pyr.levels, pyr.strides, flow, (240, 320),
                                                                         pyr.image_sizes[0], depth))
                out["fusion.fusion_conv1 (5 levels)"] = cpu_ms(
                    lambda: {k: head.fusion(v, v) for k, v in pyr.levels.items()})
    out["segmenter.segment_now (whole frame)"] = cpu_ms(lambda: seg.segment_now(frames[1]))
    # what the segmenter costs on a non-keyframe when only the fusion head reads it (frames = "on_demand": the
    # deferred segmentation runs backbone + FPN for `features`; the heads run only for whoever reads `ids`)
    out["segmenter features only (on_demand)"] = cpu_ms(lambda: seg._extract(frames[1]))
    print(f"== CPU ms per call at 320x240, median of {reps} (1 torch thread; load {os.getloadavg()[0]:.1f}) ==")
    for k, v in out.items():
        print(f"  {k:40s} {v:6.1f}")
    print(f"  added by fusion over warp_iou: {out['fusion'] - out['warp_iou']:.1f} ms CPU (segmenter decoding every "
          "frame)")
    saved = out["segmenter.segment_now (whole frame)"] - out["segmenter features only (on_demand)"]
    out["added_on_demand"] = out["fusion"] - out["warp_iou"] - saved
    print(f"  added by fusion over warp_iou on a non-keyframe with on_demand segmentation (the segmenter's own "
          f"decode skipped): {out['added_on_demand']:.1f} ms CPU")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[200, 201, 202])
    ap.add_argument("--frames", type=int, default=FRAMES)
    ap.add_argument("--domain", choices=["train", "heldout"],
                    help="render the scenes in the generator's training or held-out look (texture families and "
                         "thing sizes no training frame has: dataset.domain); default: the plain generator")
    ap.add_argument("--fusion", nargs="*", default=[], help="FusionConfig overrides KEY=JSON (e.g. z_order=false)")
    ap.add_argument("--out", type=Path, default=provenance.RESULTS_DIR / "results_vps.json",
                    help="result file (not into bench/)")
    ap.add_argument("--timing", type=int, default=0, metavar="REPS",
                    help="only the per-call CPU timing of the heads on one frame pair, REPS calls each")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    fusion_cfg = {k: json.loads(v) for k, v in (s.split("=", 1) for s in a.fusion)}
    if a.timing:
        section_timing(a.timing, fusion_cfg)
        return 0
    try:
        prov = provenance.check(a.out)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    rows = []
    for scenario in a.scenarios:
        for seed in a.seeds:
            r = run_sequence(scenario, seed, a.frames, fusion_cfg, a.domain)
            rows.append(r)
            h = r["heads"]
            print(f"{scenario:16s} seed {seed}: " + "  ".join(
                f"{n} VPQ {100 * h[n]['vpq']:.1f} PQ {100 * h[n]['pq']:.1f}" for n in HEADS)
                + f"  | fusion {h['fusion']['ms_cpu_median']:.0f} ms CPU, warp_iou {h['warp_iou']['ms_cpu_median']:.0f}"
                f" ms CPU  ({r['seconds']:.0f} s, load {r['load']:.1f})", flush=True)
            provenance.write_json(a.out, {"fusion_config": fusion_cfg, "frames": a.frames, "domain": a.domain,
                                          "runs": rows}, prov)
    print("\nmean over seeds (VPQ / PQ, x100):")
    ok = True
    for scenario in a.scenarios:
        rs = [r for r in rows if r["scenario"] == scenario]
        m = {n: (statistics.mean(r["heads"][n]["vpq"] for r in rs), statistics.mean(r["heads"][n]["pq"] for r in rs))
             for n in HEADS}
        print(f"  {scenario:16s} " + "  ".join(f"{n} {100 * v:.1f} / {100 * p:.1f}" for n, (v, p) in m.items()))
        ok &= m["fusion"][0] >= m["warp_iou"][0]
    cpu = statistics.median(r["heads"]["fusion"]["ms_cpu_median"] for r in rows)
    print(f"  [{'PASS' if ok else 'MISS'}] VPQ fusion >= warp_iou on every scenario")
    print(f"  [{'PASS' if cpu <= 50 else 'MISS'}] fusion update {cpu:.0f} ms CPU per frame at 320x240 (target <= 50)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
