"""How the generator's frames differ from real ones: image statistics the flow frontend is sensitive to.

    python bench/realism.py                                   # KITTI excerpts beside the generator's street scenes
    python bench/realism.py --synthetic driving_city/3 indoor_handheld/3 --every 5

Every sequence is read as the pipeline reads it: the KITTI excerpts in ``../shared/data`` by the ``kitti`` reader at
the default processing size (``dataset.max_pixels``), the generator's scenarios at their own 320x240, then made gray
as the flow frontend makes it (:func:`pvslam_core.imaging.to_gray`).  Per frame (every ``--every``-th), medians over
the sequence:

* **noise**: sensor noise in gray levels (Immerkaer's estimator: the mean absolute response of a Laplacian-difference
  kernel, which cancels smooth image content);
* **sharpness**: the mean gradient magnitude after a Gaussian blur of 1 px, over the mean gradient magnitude of the
  image (near 1: the image is already soft, as optics and motion blur make it; near 0: detail down to the pixel);
* **exposure step**: the 90th percentile over consecutive frames of ``|log(mean_b / mean_a)|`` (a real camera's
  auto-exposure changes the whole image's brightness between frames; the renderer's exposure is fixed);
* **weak texture**: the share of pixels whose Shi-Tomasi eigenvalue is under the flow frontend's texture scale
  (``pair_flow.TEXTURE_TAU``): the pixels whose confidence the texture term cuts;
* **clipped**: the share of pixels at 0 or 255 (saturated sky, black shadows);
* **contrast**: the standard deviation of the gray levels.

The result file (``--json``, default ``runs/bench/realism.json``) records the provenance.  Nothing here is tuned:
it says where the generator stands apart from the real frames, so that generator changes aim at what differs.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Iterable

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import provenance  # noqa: E402
from bench.matrix_jobs import KITTI  # noqa: E402

SYNTHETIC = ("driving_city/3", "busy_street/3", "moving_vehicles/3")  # the generator's streets, report seeds
REAL = ("00", "06", "01")
COLUMNS = ("noise", "sharpness", "exposure_step", "weak_texture", "clipped", "contrast")


def noise_sigma(gray: np.ndarray) -> float:
    """Immerkaer's noise estimate (gray levels) of a uint8 image: ``sqrt(pi/2) / (6 (W-2)(H-2)) * sum |I * N|``."""
    import cv2

    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    resp = cv2.filter2D(gray.astype(np.float32), -1, kernel)[1:-1, 1:-1]
    h, w = gray.shape
    return float(math.sqrt(math.pi / 2) * np.abs(resp).sum() / (6.0 * (w - 2) * (h - 2)))


def _grad(img: np.ndarray) -> float:
    import cv2

    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return float(np.sqrt(gx * gx + gy * gy).mean())


def frame_stats(gray: np.ndarray, tau: float) -> dict[str, float]:
    """The per-frame statistics of the module docstring (all but the exposure step) of a uint8 gray image."""
    import cv2

    g = gray.astype(np.float32)
    lam = np.maximum(cv2.cornerMinEigenVal(gray, blockSize=5, ksize=3), 0.0)
    return {"noise": noise_sigma(gray),
            "sharpness": _grad(cv2.GaussianBlur(g, (0, 0), 1.0)) / max(_grad(g), 1e-9),
            "weak_texture": float((lam < tau).mean()),
            "clipped": float(((gray == 0) | (gray == 255)).mean()),
            "contrast": float(g.std()),
            "mean": float(g.mean())}


def sequence_stats(grays: Iterable[np.ndarray], tau: float) -> dict[str, float]:
    """Medians over frames of :func:`frame_stats`; the exposure step from consecutive frames' means."""
    per = [frame_stats(g, tau) for g in grays]
    if len(per) < 2:
        raise ValueError("need at least two frames")
    out = {k: float(np.median([p[k] for p in per])) for k in COLUMNS if k != "exposure_step"}
    means = np.array([p["mean"] for p in per])
    out["exposure_step"] = float(np.quantile(np.abs(np.diff(np.log(np.maximum(means, 1.0)))), 0.9))
    out["frames"] = len(per)
    return out


def kitti_grays(seq: str, every: int) -> tuple[list[np.ndarray], str]:
    """Gray frames of a KITTI excerpt at the default processing size, every ``every``-th consecutive pair kept
    together (the exposure step compares neighbours)."""
    from pvslam_core.imaging import to_gray
    from pvslam_plugins.datasets.kitti.config import KittiConfig
    from pvslam_plugins.datasets.kitti.reader import make_reader

    reader = make_reader(KittiConfig(path=str(KITTI), sequence=seq))
    grays = [to_gray(f.image) for i, f in enumerate(reader) if i % every in (0, 1)]
    return grays, "x".join(str(v) for v in grays[0].shape[::-1])


def synthetic_grays(cell: str, every: int) -> tuple[list[np.ndarray], str]:
    """Gray frames of a generator scenario ``name/seed`` at 320x240 (its cached sequence folder)."""
    import cv2

    from pvslam_plugins.datasets.synthetic.generator import ensure_cached

    name, seed = cell.split("/")
    d = ensure_cached(name, num_frames=None, seed=int(seed), width=320, height=240, progress=False)
    files = sorted((d / "rgb").iterdir())
    keep = [p for i, p in enumerate(files) if i % every in (0, 1)]
    grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in keep]
    return grays, "x".join(str(v) for v in grays[0].shape[::-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", nargs="*", default=list(REAL), help="KITTI excerpts of ../shared/data")
    ap.add_argument("--synthetic", nargs="*", default=list(SYNTHETIC), help="generator scenario/seed cells")
    ap.add_argument("--every", type=int, default=4, help="keep frame pairs every N frames")
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "realism.json"))
    args = ap.parse_args(argv)
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    from pvslam_plugins.frontends.flow.pair_flow import TEXTURE_TAU

    rows = {}
    jobs = [(f"kitti {s}", kitti_grays, s) for s in args.real if (KITTI / "sequences" / s).is_dir()]
    jobs += [(c, synthetic_grays, c) for c in args.synthetic]
    print(f"{'sequence':<22} {'size':>8} " + " ".join(f"{c:>13}" for c in COLUMNS))
    for name, read, arg in jobs:
        grays, size = read(arg, args.every)
        st = sequence_stats(grays, TEXTURE_TAU)
        st["size"] = size
        rows[name] = st
        print(f"{name:<22} {size:>8} " + " ".join(f"{st[c]:>13.3f}" for c in COLUMNS), flush=True)
    provenance.write_json(args.json, {"every": args.every, "texture_tau": TEXTURE_TAU, "rows": rows}, prov)
    return 0


if __name__ == "__main__":
    sys.exit(main())
