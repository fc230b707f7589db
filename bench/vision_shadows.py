"""Where the top corpus' worst sides lie: each side's offset against where the holder's
cast shadow's edge lies beside it.

    python bench/vision_shadows.py                       # the bench's corpus, 1001 scenes
    python bench/vision_shadows.py --seeds 2124,9100     # other corpora
    python bench/vision_shadows.py --quick               # CI-sized (42 scenes)

A random top scene's holder casts a shadow: its outline (with the sample plate's) shifted
by ``params["cast_shadow"]["offset_px"]`` and blurred by its ``blur_px``
(:func:`drivers.sim.scenes.random_top_scene`). Beside each side, that shadow's edge lies
``d`` px out (the offset along the side's outward normal; negative: under the holder).
Its penumbra, the camera's blur added, is sqrt(shadow blur^2 + frame blur^2) wide, and
the table bins the sides by ``d`` in those widths: a penumbra across the side (``d``
within about one width) bends the floor right at the edge, where the edge model and the
penumbra fit (:func:`alignd.vision.profile_fit._penumbra_bend`) trade off. Each side's
offset is the mean of its two corners' displacements along its outward normal (px, +
outward). Uncompressed frames only (JPEG's own errors left out); a sample plate's side is
left out (the shadow there is the plate's, not the holder's). docs/vision.md, "Where the
worst sides lie", reads the table.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import itertools  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the vision benches' helpers

from vision import print_table  # noqa: E402
from vision_bounds import scene_number  # noqa: E402

from alignd.errors import VisionError  # noqa: E402
from alignd.vision.holder import track_holder  # noqa: E402
from alignd.vision.lens import Lens  # noqa: E402
from drivers.sim.scenes import TOP_CATEGORIES, TopSceneSample, random_top_scene  # noqa: E402

# the bins' edges: where the shadow's edge lies, in penumbra widths out from the side
_BINS = (-math.inf, -3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0, 5.0, math.inf)
_WORST = 10  # the worst sides listed under the table


@dataclass(frozen=True)
class SideRecord:
    """One side of one found holder: its offset (px, + outward) and, with a cast shadow,
    where that shadow's edge lies (px out) and its penumbra's width (px)."""

    seed: int
    scene: int
    side: int
    offset_px: float
    shadow_px: float  # nan: no cast shadow
    penumbra_px: float
    depth: float

    @property
    def widths_out(self) -> float:
        return self.shadow_px / self.penumbra_px


def scene_sides(seed: int, i: int, sc: TopSceneSample) -> list[SideRecord]:
    """The sides of ``sc``'s holder as found (none where it was not, or compressed),
    in the scene's own corner order (side 0 along the sample plate, if any)."""
    if sc.encoding.jpeg_quality is not None:
        return []
    lens = Lens(sc.lens[0], sc.lens[1], sc.lens[2]) if sc.lens else None
    try:
        det = track_holder(sc.image, expected_size_px=sc.expected_size_px, lens=lens)
    except VisionError:
        return []
    if not det.ok:
        return []
    truth = np.asarray(sc.corners_px, float)
    # each true corner's nearest found one (either winding)
    near = np.argmin(np.linalg.norm(det.corners_px[None] - truth[:, None], axis=2), axis=1)
    got = det.corners_px[near]
    cast = sc.params.get("cast_shadow")
    plate = scene_number(sc.params, "sample_px") > 0 if "sample_px" in sc.params else False
    out = []
    for k in range(4):
        if k == 0 and plate:
            continue
        a, b = truth[k], truth[(k + 1) % 4]
        t = (b - a) / np.linalg.norm(b - a)
        n = np.array([-t[1], t[0]])
        if float(np.dot(truth.mean(axis=0) - a, n)) > 0:
            n = -n
        off = 0.5 * float(np.dot(got[k] - a, n) + np.dot(got[(k + 1) % 4] - b, n))
        if isinstance(cast, dict):
            d = float(np.dot(np.asarray(cast["offset_px"], float), n))
            width = math.hypot(float(cast["blur_px"]), scene_number(sc.params, "blur_px"))
            depth = float(cast["depth"])
        else:
            d, width, depth = math.nan, math.nan, math.nan
        out.append(SideRecord(seed, i, k, off, d, width, depth))
    return out


def corpus_sides(seed: int, n: int) -> list[SideRecord]:
    """Every side found of ``n`` random top scenes of ``seed`` (1280 x 720, the
    categories in turn, as bench/vision.py draws them)."""
    rng = np.random.default_rng(seed)
    out: list[SideRecord] = []
    for i in range(n):
        sc = random_top_scene(rng, TOP_CATEGORIES[i % len(TOP_CATEGORIES)])
        out += scene_sides(seed, i, sc)
    return out


def _row(label: str, sides: list[SideRecord]) -> tuple[str, ...]:
    if not sides:
        return (label, "0", "", "", "", "", "")
    o = np.abs(np.array([s.offset_px for s in sides]))
    return (label, str(o.size), f"{math.sqrt(float(np.mean(o * o))):.3f}",
            f"{float(np.mean([s.offset_px for s in sides])):+.3f}", f"{float(np.max(o)):.2f}",
            str(int(np.sum(o > 0.15))), str(int(np.sum(o > 0.25))))


def print_sides(sides: list[SideRecord]) -> None:
    shaded = [s for s in sides if not math.isnan(s.shadow_px)]
    rows = [_row("no cast shadow", [s for s in sides if math.isnan(s.shadow_px)])]
    rows += [_row(f"  {lo:g} to {hi:g} penumbra widths",
                  [s for s in shaded if lo <= s.widths_out < hi])
             for lo, hi in itertools.pairwise(_BINS)]
    print_table(("where the shadow edge lies", "sides", "RMS px", "mean px", "max px",
                 "> 0.15", "> 0.25"), rows)
    worst = sorted(sides, key=lambda s: -abs(s.offset_px))[:_WORST]
    print(f"\nthe {len(worst)} worst sides (shadow edge px out / penumbra width px / depth)")
    for s in worst:
        where = ("no cast shadow" if math.isnan(s.shadow_px) else
                 f"shadow edge {s.shadow_px:+.2f} px / {s.penumbra_px:.2f} px "
                 f"({s.widths_out:+.2f} widths), depth {s.depth:.2f}")
        print(f"  seed {s.seed} #{s.scene} side {s.side}: {s.offset_px:+.3f} px; {where}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="2024",
                    help="corpora's seeds, comma-separated (default 2024, bench/vision.py's)")
    ap.add_argument("--scenes", type=int, default=1001, help="scenes per corpus")
    ap.add_argument("--quick", action="store_true", help="few scenes (CI)")
    args = ap.parse_args()
    n = 42 if args.quick else args.scenes
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    sides = [r for seed in seeds for r in corpus_sides(seed, n)]
    print(f"top corpora {', '.join(map(str, seeds))} ({n} scenes each): uncompressed sides "
          "found, their offsets (px, + outward) by where the holder's cast shadow's edge "
          "lies beside them")
    print_sides(sides)


if __name__ == "__main__":
    main()
