"""Joint centres of a scaled OpenSim model and of its static trial, in every frame (test data).

The reference for joint-centre accuracy on ``opensim_models/Hamner``, built the way a lab
builds it (the calibrated anatomical systems technique):

* the hip is the model's ``hip_r``/``hip_l`` joint location in the pelvis, placed by the
  pelvis markers (Horn's least-squares rigid fit of the model's pelvis marker locations to the
  static trial's);
* the knee and ankle are the midpoints of the medial and lateral epicondyle and malleolus
  markers of the static trial (the model's ``RKJC``/``RAJC`` sit exactly there);
* each is carried into every frame of a dynamic trial by the technical cluster of one segment
  (its pose from Horn's fit of the static trial's cluster to the frame's).

The model's cluster marker locations are generic (the scale tool did not move them: their
distances differ from the subject's by up to 20 cm), so only the static trial places them.
Only the .osim's XML is read; OpenSim is not needed.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class OsimModel:
    marker_body: dict[str, str]  # marker -> body
    marker_location: dict[str, np.ndarray]  # marker -> (3,) in its body's frame [m]
    joint_location: dict[str, tuple[str, np.ndarray]]  # joint -> (parent body, (3,) in it [m])


def read_osim(path: Path) -> OsimModel:
    root = ET.parse(path).getroot()
    body, loc = {}, {}
    for m in root.iter("Marker"):
        frame = m.findtext("socket_parent_frame") or m.findtext("body") or ""
        body[m.get("name")] = frame.split("/")[-1]
        loc[m.get("name")] = np.array([float(v) for v in m.findtext("location").split()])
    joints = {}
    for tag in ("CustomJoint", "PinJoint", "WeldJoint", "BallJoint"):
        for j in root.iter(tag):
            parent_name = j.findtext("socket_parent_frame")
            for f in j.iter("PhysicalOffsetFrame"):
                if f.get("name") == parent_name:
                    t = np.array([float(v) for v in f.findtext("translation").split()])
                    joints[j.get("name")] = (f.findtext("socket_parent").split("/")[-1], t)
    return OsimModel(body, loc, joints)


def _horn(model_pts: np.ndarray, lab_pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with lab ~ R @ model + t (least squares; model_pts, lab_pts: (n, 3))."""
    mc, lc = model_pts.mean(0), lab_pts.mean(0)
    u, _, vt = np.linalg.svd((lab_pts - lc).T @ (model_pts - mc))
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, 1.0, d]) @ vt
    return r, lc - r @ mc


def body_points_in_lab(model: OsimModel, labels, positions, body: str, points: np.ndarray,
                       marker_map=None) -> tuple[np.ndarray, np.ndarray]:
    """``points`` (k, 3) fixed in ``body`` carried into the lab in every frame: (frames, k, 3),
    NaN where fewer than three of the body's markers are seen; and the per-frame RMS marker
    residual of the body's rigid fit [m]. ``labels``/``positions`` are the recording's (metres)."""
    marker_map = marker_map or {}
    names = [n for n, b in model.marker_body.items() if b == body]
    index = {lab: i for i, lab in enumerate(labels)}
    cols = [(index[marker_map.get(n, n)], model.marker_location[n]) for n in names if marker_map.get(n, n) in index]
    nf = positions.shape[0]
    out = np.full((nf, len(points), 3), np.nan)
    resid = np.full(nf, np.nan)
    if len(cols) < 3:
        return out, resid
    idx = np.array([c[0] for c in cols])
    mpts = np.stack([c[1] for c in cols])
    for f in range(nf):
        lab = positions[f, idx]
        ok = np.isfinite(lab).all(1)
        if ok.sum() < 3:
            continue
        r, t = _horn(mpts[ok], lab[ok])
        out[f] = points @ r.T + t
        resid[f] = np.sqrt(np.mean(np.sum((mpts[ok] @ r.T + t - lab[ok]) ** 2, -1)))
    return out, resid


def horn(model_pts: np.ndarray, lab_pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return _horn(model_pts, lab_pts)


def carry(static_labels, static_positions, points: np.ndarray, cluster, labels, positions) -> np.ndarray:
    """Points (k, 3) given in the static trial's lab frame, carried into every frame of a
    dynamic trial by the rigid motion of the ``cluster`` markers: (frames, k, 3)."""
    cluster = [c for c in cluster if c in static_labels and c in labels]
    si = [list(static_labels).index(c) for c in cluster]
    di = [list(labels).index(c) for c in cluster]
    ref = np.nanmedian(static_positions[:, si], axis=0)
    out = np.full((positions.shape[0], len(points), 3), np.nan)
    for f in range(positions.shape[0]):
        lab = positions[f, di]
        ok = np.isfinite(lab).all(1)
        if ok.sum() < 3:
            continue
        r, t = _horn(ref[ok], lab[ok])
        out[f] = points @ r.T + t
    return out


def hamner_joint_centres(model: OsimModel, static, trial) -> dict[str, np.ndarray]:
    """``{"R hip": (frames, 3), "R knee": ..., "R ankle": ..., "L ...": ...}`` in ``trial``'s frames
    (``static`` and ``trial`` are jaxskel Trials of Hamner's static and a dynamic trial)."""
    sl, sp = static.labels, static.positions
    pelvis = ["R.ASIS", "L.ASIS", "V.Sacral"]
    hips = np.stack([model.joint_location["hip_r"][1], model.joint_location["hip_l"][1]])
    hip_static = np.nanmedian(body_points_in_lab(model, sl, sp, "pelvis", hips)[0], axis=0)
    out = {}
    for i, s in enumerate("RL"):
        out[f"{s} hip"] = carry(sl, sp, hip_static[i:i + 1], pelvis, trial.labels, trial.positions)[:, 0]
        mid = {}
        for joint, pair in (("knee", ("Knee.Lat", "Knee.Med")), ("ankle", ("Ankle.Lat", "Ankle.Med"))):
            idx = [list(sl).index(f"{s}.{m}") for m in pair]
            mid[joint] = np.nanmedian(sp[:, idx].mean(1), axis=0)
        thigh = [f"{s}.Thigh.{m}" for m in ("Upper", "Front", "Rear")] + [f"{s}.Knee.Lat"]
        shank = [f"{s}.Shank.{m}" for m in ("Upper", "Front", "Rear")] + [f"{s}.Ankle.Lat"]
        out[f"{s} knee"] = carry(sl, sp, mid["knee"][None], thigh, trial.labels, trial.positions)[:, 0]
        out[f"{s} ankle"] = carry(sl, sp, mid["ankle"][None], shank, trial.labels, trial.positions)[:, 0]
    return out
