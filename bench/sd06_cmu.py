"""SD06 joint angles of the shared CMU take 02_05, elbows and knees, against two references.

What a flexion angle is compared with (none comes from SD06):

* **the joint-centre angle**: flexion = 180 degrees minus the angle at the joint between
  the fitted joint centres above and below it (shoulder - elbow - wrist markers' midpoint
  ``(xWRA + xWRB) / 2``, the forearm having no distal joint in this fit; hip - knee -
  ankle), taken relative to the default-pose frame. For a hinge this is the flexion,
  whatever axes SD06 finds;
* **the skin markers' angle**: 180 degrees minus the angle at the knee marker between the
  thigh and ankle markers (``xTHI - xKNE - xANK``), or at the elbow marker between the
  upper-arm marker and the wrist markers' midpoint (``xUPA - xELB - xWR``), measured
  markers only (no fit, no joint centre); the markers sit off the bones, so it is
  compared about its mean (RMS of the difference minus its mean);
* **the subject's CMU skeleton** (``timegan_cmu/02.asf``, legs only) declares each knee
  (``ltibia``, ``rtibia``) with one degree of freedom (``dof rx``): a hinge.

Each joint's first SD06 angle is compared (sign aligned) with both: correlation and RMS
difference over the take, with the default axis count (``axis_count="anatomy"``: knees
and elbows one axis) and with ``axis_count="data"`` (every count from the one-or-two-axes
test). The fit is ``jaxskel.fit_skeleton`` with defaults, the parameterisation
``jaxskel.sd06.parameterize`` with defaults (automatic calibration: this punching take
has no calibration protocol, so every joint falls back to every frame).

Two more takes of the set (a CMU walk, an HDM05 take) get the same comparison with the
skin markers' angle (``OTHER_TAKES``).

Usage::

    PYTHONPATH=. python bench/sd06_cmu.py [--out docs/bench/sd06_cmu.md]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
DATA = REAL / "nimblephysics" / "cmu_02_05.c3d"
#: Other takes of the same 41-marker set: a CMU walk and an HDM05 take.
OTHER_TAKES = ("c3d_to_xyz_cmu/01_01.c3d", "dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d")


def _angle_at(mid: np.ndarray, above: np.ndarray, below: np.ndarray) -> np.ndarray:
    """180 degrees minus the angle at ``mid`` between ``above`` and ``below`` (per frame)."""
    u, v = above - mid, below - mid
    cos = np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def other_take_rows(rel: str, segment_parts) -> list[str]:
    """Per joint that the defaults give one axis from the anatomy: its count and the correlation
    of its first angle with the skin markers' angle, with the defaults and with the data's count."""
    import jaxskel

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = jaxskel.fit_skeleton(jaxskel.load(REAL / rel))
        anatomy = jaxskel.sd06.parameterize(res.skeleton, res.motion)
        data = jaxskel.sd06.parameterize(res.skeleton, res.motion, anatomy.normalization, axis_count="data")
    parts = segment_parts(res.trial.labels, res.segmentation.marker_segment)
    labels = [str(x).upper().split(":")[-1] for x in res.trial.labels]
    raw = np.where(np.asarray(res.trial.mask)[..., None], np.asarray(res.trial.positions), np.nan)
    rows = []
    for j in np.flatnonzero(anatomy.axis_count_source == "anatomy"):
        above, below = (parts[s] for s in res.skeleton.edges[j])
        side = above[0]
        names = (f"{side}THI", f"{side}KNE", f"{side}ANK") if "thigh" in above else (
            f"{side}UPA", f"{side}ELB", f"{side}WRA")
        upper, mid, lower = (raw[:, labels.index(n)] for n in names)
        skin = _angle_at(mid, upper, lower)
        seen = np.isfinite(skin)
        corr = [abs(np.corrcoef(p.angles[seen, j, 0], skin[seen])[0, 1]) for p in (anatomy, data)]
        rows.append(f"| {rel} | {above} - {below} | {np.degrees(anatomy.hinge_rms[j]):.1f} | {corr[0]:.3f} | "
                    f"{data.n_axes[j]} | {corr[1]:.3f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "sd06_cmu.md")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from human_markers import segment_parts

    import jaxskel

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial = jaxskel.load(DATA)
        res = jaxskel.fit_skeleton(trial)
    parts = segment_parts(res.trial.labels, res.segmentation.marker_segment)
    edges = res.skeleton.edges

    def joint(a: str, b: str) -> int:
        (j,) = [j for j, (p, c) in enumerate(edges) if {parts[p], parts[c]} == {a, b}]
        return j

    centres = res.motion.joint_positions
    markers = res.motion.fitted_markers
    raw = np.where(np.asarray(res.trial.mask)[..., None], np.asarray(res.trial.positions), np.nan)
    labels = [str(x).upper() for x in res.trial.labels]

    def marker(name: str, measured: bool = False) -> np.ndarray:
        (i,) = [i for i, x in enumerate(labels) if x.endswith(name)]
        return (raw if measured else markers)[:, i]

    flexion = _angle_at

    cases = {}
    for s in "RL":
        elbow, shoulder = joint(f"{s} upper arm", f"{s} forearm"), joint("thorax", f"{s} upper arm")
        wrist = 0.5 * (marker(f"{s}WRA") + marker(f"{s}WRB"))
        measured_wrist = 0.5 * (marker(f"{s}WRA", True) + marker(f"{s}WRB", True))
        cases[f"{s} elbow"] = (elbow, flexion(centres[:, elbow], centres[:, shoulder], wrist),
                               flexion(marker(f"{s}ELB", True), marker(f"{s}UPA", True), measured_wrist))
        knee, hip, ankle = (joint(f"{s} thigh", f"{s} shank"), joint("pelvis", f"{s} thigh"),
                            joint(f"{s} shank", f"{s} foot"))
        cases[f"{s} knee"] = (knee, flexion(centres[:, knee], centres[:, hip], centres[:, ankle]),
                              flexion(marker(f"{s}KNE", True), marker(f"{s}THI", True), marker(f"{s}ANK", True)))
    rows, spins = [], []
    marker_segment = np.asarray(res.skeleton.marker_segment)
    for label, kw in (("default (`axis_count=\"anatomy\"`)", {}), ('`axis_count="data"`', {"axis_count": "data"})):
        param = jaxskel.sd06.parameterize(res.skeleton, res.motion, **kw)
        d = param.normalization.default_frame
        for name, (j, geo, on_skin) in cases.items():
            ref = geo - geo[d]
            seen = np.isfinite(on_skin)
            skin_first = np.degrees(param.angles[seen, j, 0])
            skin_corr = np.corrcoef(skin_first, on_skin[seen])[0, 1]
            # The skin markers' angle has its own offset (they sit off the bones): compare changes.
            skin_diff = np.sign(skin_corr) * skin_first - on_skin[seen]
            skin_rms = float(np.sqrt(np.mean((skin_diff - np.mean(skin_diff)) ** 2)))
            first = np.degrees(param.angles[:, j, 0])
            corr = np.corrcoef(first, ref)[0, 1]
            rms = float(np.sqrt(np.mean((np.sign(corr) * first - ref) ** 2)))
            # The angle that best follows the flexion (with two axes: either), sign aligned.
            cands = [np.degrees(param.angles[:, j, k]) for k in range(param.n_axes[j])]
            corrs = [np.corrcoef(c, ref)[0, 1] for c in cands]
            k = int(np.argmax(np.abs(corrs)))
            best_rms = float(np.sqrt(np.mean((np.sign(corrs[k]) * cands[k] - ref) ** 2)))
            rows.append(f"| {name} | {label} | {param.n_axes[j]} | {np.degrees(param.hinge_rms[j]):.1f} | "
                        f"{np.ptp(geo):.1f} | {abs(corr):.3f} | {rms:.1f} | "
                        f"{np.ptp(np.degrees(param.angles[:, j, 1])):.1f} | {'first' if k == 0 else 'second'}: "
                        f"{abs(corrs[k]):.3f}, {best_rms:.1f} | {abs(skin_corr):.3f}, {skin_rms:.1f} |")
            if kw == {}:
                # How far the child's long axis leaves the one-axis circle, in the parent limb's frame.
                off = np.degrees(np.arcsin(np.clip(param.samples[:, j] @ param.axes[j][0], -1.0, 1.0)))
                lo, hi = np.percentile(off - np.median(off), [5, 95])
                parent = int(edges[j][0])
                on_parent = [res.trial.labels[i] for i in np.flatnonzero(marker_segment == parent)]
                spins.append(f"| {name} | {param.axis_count_source[j]} | {lo:+.1f} to {hi:+.1f} | "
                             f"{np.degrees(param.noise[j]):.2f} | "
                             f"{parts[parent]}: {' '.join(map(str, on_parent))} |")
    lines = [
        "# SD06 on CMU 02_05: elbows and knees",
        "",
        "Command: `PYTHONPATH=. python bench/sd06_cmu.py`. References: the joint-centre flexion, the skin markers' "
        "angle and the subject's CMU skeleton, whose knees are hinges (`bench/sd06_cmu.py` docstring).",
        "",
        "| joint | axis count | axes | off-one-axis RMS (deg) | flexion range, joint centres (deg) | "
        "correlation, first angle vs joint-centre flexion | RMS difference (deg) | second angle's range (deg) | "
        "angle that follows the flexion best: correlation, RMS difference (deg) | first angle vs the skin markers' "
        "angle: correlation, RMS difference about the mean (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Where the swing leaves one axis (the defaults' one-axis fit): the child's long axis, seen in the parent "
        "limb's frame, off the one-axis circle (5th to 95th percentile, degrees), the estimated white rotation "
        "noise, and the parent segment's markers.",
        "",
        "| joint | axis count from | off the circle, p5 to p95 (deg) | rotation noise (deg) | "
        "parent segment: its markers |",
        "|---|---|---|---|---|",
        *spins,
        "",
        "With the defaults the knees and elbows are found from the skeleton's shape (`jaxskel.sd06._anatomy`: "
        "in each limb the joint between its two longest bones, with a partner limb of the same length on the same "
        "segment) and get the hinge's one "
        "axis, as the paper takes the degrees of freedom from the anatomy ([Kea05]) and only the axes from the "
        "data. Their first angle then follows both references: the elbows the joint-centre flexion to about 1 "
        "degree RMS, the knees the skin markers' angle (thigh - knee - ankle markers) to about 2 degrees about "
        "its mean, correlation above 0.99 for all four. The right knee departs from its joint-centre flexion "
        "(11.7 degrees RMS, slope 1.2) because that reference uses the fitted right hip, which sits too far "
        "from the knee (the right thigh is 74 mm longer than the .asf's femur: `tests/test_real_skeleton.py`); "
        "the skin markers' angle does not use the hip. With `axis_count=\"data\"` (the count of the one-or-two-"
        "axes test alone) both elbows and the right knee get two axes, because their swing leaves one axis by "
        "more than the tolerance (4 degrees, noise removed); the flexion is then shared between two axes 36-38 "
        "degrees apart, and neither angle alone is the flexion (the first angle's correlation 0.15-0.48). What "
        "leaves the circle is not noise and not flexion: the forearm's long axis, seen in the upper arm's frame, "
        "swings tens of degrees off the flexion circle, more than an elbow can abduct, in slow excursions (the "
        "white rotation noise is a tenth of a degree). The parents of the joints that leave their circle most "
        "carry two markers each (right upper arm, right thigh), one of them at the joint: their fitted spin "
        "about their own long axis rests on a lever of a few centimetres, so soft tissue can turn the parent's "
        "frame, and with it the plane the hinge moves in. `tests/sd06/test_anatomy.py` reproduces this with "
        "known angles (a thigh spun by +-15 degrees about its long axis: two axes and a 20+ degree flexion error "
        "from the data alone, one axis and under 1.5 degrees with the anatomy).",
        "",
        "## Two more takes of the 41-marker set",
        "",
        "The joints the defaults give one axis from the anatomy (`axis_count_source == \"anatomy\"`), the "
        "correlation of their first angle with the skin markers' angle (thigh - knee - ankle, or upper-arm - "
        "elbow - wrist marker `xWRA`), with the defaults and with `axis_count=\"data\"`.",
        "",
        "| take | joint | off-one-axis RMS (deg) | correlation, defaults (one axis) | axes, data's count | "
        "correlation, data's count |",
        "|---|---|---|---|---|---|",
        *[row for rel in OTHER_TAKES for row in other_take_rows(rel, segment_parts)],
        "",
    ]
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
