"""SD06 joint angles of the shared CMU take 02_05, elbows and knees, against two references.

What a flexion angle is compared with (neither comes from SD06):

* **the joint-centre angle**: flexion = 180 degrees minus the angle at the joint between
  the fitted joint centres above and below it (shoulder - elbow - wrist markers' midpoint
  ``(xWRA + xWRB) / 2``, the forearm having no distal joint in this fit; hip - knee -
  ankle), taken relative to the default-pose frame. For a hinge this is the flexion,
  whatever axes SD06 finds;
* **the subject's CMU skeleton** (``timegan_cmu/02.asf``, legs only) declares each knee
  (``ltibia``, ``rtibia``) with one degree of freedom (``dof rx``): a hinge.

Each joint's first SD06 angle is compared (sign aligned) with the joint-centre flexion:
correlation and RMS difference over the take, for the automatic axis count and with
``n_axes=1`` at the elbows and knees (the ASF's hinge). The fit is ``jaxskel.fit_skeleton``
with defaults, the parameterisation ``jaxskel.sd06.parameterize`` with defaults
(automatic calibration: this punching take has no calibration protocol, so every
joint falls back to every frame).

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
DATA = ROOT.parent / "shared" / "data" / "real" / "nimblephysics" / "cmu_02_05.c3d"


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
    labels = [str(x).upper() for x in res.trial.labels]

    def marker(name: str) -> np.ndarray:
        (i,) = [i for i, x in enumerate(labels) if x.endswith(name)]
        return markers[:, i]

    def flexion(mid: int, above: np.ndarray, below: np.ndarray) -> np.ndarray:
        u, v = above - centres[:, mid], below - centres[:, mid]
        cos = np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    cases = {}
    for s in "RL":
        elbow, shoulder = joint(f"{s} upper arm", f"{s} forearm"), joint("thorax", f"{s} upper arm")
        cases[f"{s} elbow"] = (elbow, flexion(elbow, centres[:, shoulder], 0.5 * (marker(f"{s}WRA") + marker(f"{s}WRB"))))
        knee, hip, ankle = (joint(f"{s} thigh", f"{s} shank"), joint("pelvis", f"{s} thigh"),
                            joint(f"{s} shank", f"{s} foot"))
        cases[f"{s} knee"] = (knee, flexion(knee, centres[:, hip], centres[:, ankle]))
    rows, spins = [], []
    marker_segment = np.asarray(res.skeleton.marker_segment)
    for label, kw in (("automatic", {}), ("`n_axes=1`", {"n_axes": {j: 1 for j, _ in cases.values()}})):
        param = jaxskel.sd06.parameterize(res.skeleton, res.motion, **kw)
        d = param.normalization.default_frame
        for name, (j, geo) in cases.items():
            ref = geo - geo[d]
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
                        f"{abs(corrs[k]):.3f}, {best_rms:.1f} |")
            if label != "automatic":
                # How far the child's long axis leaves the one-axis circle, in the parent limb's frame.
                off = np.degrees(np.arcsin(np.clip(param.samples[:, j] @ param.axes[j][0], -1.0, 1.0)))
                lo, hi = np.percentile(off - np.median(off), [5, 95])
                parent = int(edges[j][0])
                on_parent = [res.trial.labels[i] for i in np.flatnonzero(marker_segment == parent)]
                spins.append(f"| {name} | {lo:+.1f} to {hi:+.1f} | {np.degrees(param.noise[j]):.2f} | "
                             f"{parts[parent]}: {' '.join(map(str, on_parent))} |")
    lines = [
        "# SD06 on CMU 02_05: elbows and knees",
        "",
        "Command: `PYTHONPATH=. python bench/sd06_cmu.py`. References: the joint-centre flexion and the subject's "
        "CMU skeleton, whose knees are hinges (`bench/sd06_cmu.py` docstring).",
        "",
        "| joint | axis count | axes | off-one-axis RMS (deg) | flexion range, joint centres (deg) | "
        "correlation, first angle vs joint-centre flexion | RMS difference (deg) | second angle's range (deg) | "
        "angle that follows the flexion best: correlation, RMS difference (deg) |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Where the swing leaves one axis (one-axis fit, `n_axes=1`): the child's long axis, seen in the parent "
        "limb's frame, off the one-axis circle (5th to 95th percentile, degrees), the estimated white rotation "
        "noise, and the parent segment's markers.",
        "",
        "| joint | off the circle, p5 to p95 (deg) | rotation noise (deg) | parent segment: its markers |",
        "|---|---|---|---|",
        *spins,
        "",
        "The automatic count gives two axes where a joint's swing leaves one axis by more than the tolerance "
        "(4 degrees, noise removed): both elbows and the right knee here. With two axes the second (parent-fixed) "
        "axis is the flexion axis and its angle follows the flexion best (last column), while the first angle "
        "turns by as much again: the flexion is shared between two axes, and for the right elbow and knee, whose "
        "axes lie 36-38 degrees apart, neither angle alone is the flexion. With the defaults the right elbow and "
        "knee are therefore not sensible on this take. With one axis, as the CMU skeleton declares the knees, the "
        "elbows and the left knee follow the joint-centre flexion to about 1 degree RMS; the right knee to about "
        "12 (slope 1.2 against the joint-centre angle). What leaves the circle is not noise and not flexion: the "
        "forearm's long axis, seen in the upper arm's frame, swings tens of degrees off the flexion circle, more "
        "than an elbow can abduct, in slow excursions (the white rotation noise is a tenth of a degree). The "
        "parents of the joints that leave their circle most carry two markers each (right upper arm, right "
        "thigh), one of them at the joint: their fitted spin about their own long axis rests on a lever of a "
        "few centimetres, so soft tissue can turn the parent's frame, and with it the plane the hinge moves in "
        "(a likely cause, not a proof: the left thigh carries two markers too, and its knee stays within 4 "
        "degrees). "
        "Replacing the forearm's long axis by the elbow-to-wrist direction changed nothing (0.8 and 2.8 degrees "
        "apart; same counts), and merging axes closer than 45 degrees broke the synthetic two-axis joints of "
        "combined movement (both tried, not kept). Pass `n_axes` where the anatomy is known.",
        "",
    ]
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
