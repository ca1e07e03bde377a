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
from helpers import horn_align


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


def _follow(reference: np.ndarray, measured: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``points`` (k, 3), given in the frame of the marker cloud ``reference`` (n, 3), carried
    into every frame of ``measured`` (F, n, 3) by Horn's fit of the cloud: (F, k, 3) and the
    fit's RMS marker residual per frame; NaN where fewer than three markers are seen."""
    out = np.full((measured.shape[0], len(points), 3), np.nan)
    resid = np.full(measured.shape[0], np.nan)
    for f, lab in enumerate(measured):
        ok = np.isfinite(lab).all(1)
        if ok.sum() < 3:
            continue
        r, t = horn_align(reference[ok], lab[ok])
        out[f] = points @ r.T + t
        resid[f] = np.sqrt(np.mean(np.sum((reference[ok] @ r.T + t - lab[ok]) ** 2, -1)))
    return out, resid


def body_points_in_lab(model: OsimModel, labels, positions, body: str,
                       points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``points`` (k, 3) fixed in ``body`` carried into the lab in every frame: (frames, k, 3),
    NaN where fewer than three of the body's markers are seen; and the per-frame RMS marker
    residual of the body's rigid fit [m]. ``labels``/``positions`` are the recording's (metres)."""
    cols = [(list(labels).index(n), model.marker_location[n])
            for n, b in model.marker_body.items() if b == body and n in labels]
    if len(cols) < 3:
        return np.full((positions.shape[0], len(points), 3), np.nan), np.full(positions.shape[0], np.nan)
    return _follow(np.stack([c[1] for c in cols]), positions[:, [c[0] for c in cols]], points)


def carry(static_labels, static_positions, points: np.ndarray, cluster, labels, positions) -> np.ndarray:
    """Points (k, 3) given in the static trial's lab frame, carried into every frame of a
    dynamic trial by the rigid motion of the ``cluster`` markers: (frames, k, 3)."""
    cluster = [c for c in cluster if c in static_labels and c in labels]
    si = [list(static_labels).index(c) for c in cluster]
    di = [list(labels).index(c) for c in cluster]
    return _follow(np.nanmedian(static_positions[:, si], axis=0), positions[:, di], points)[0]


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
