"""Body parts of the standard marker sets in the shared recordings, and the .asf skeletons.

Sets: the 41-marker Vicon set of CMU and HDM05 (and its Plug-in-Gait spellings), Clouthier
et al.'s 62-marker cluster set (``auto_marker_label``: four-marker limb clusters, head,
back, pelvis, acromion, wrist, hand, ankle and foot markers), numediart's 68-marker set
and biobuddy's lower-limb calibration set.

Used to judge a fitted tree on real recordings without ground-truth segment
labels: a segment is named after the body part most of its markers sit on, and an
edge is plausible when it joins parts that are adjacent in a human skeleton.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Marker -> body part. Markers placed on a joint (knee, ankle, elbow, wrist,
#: shoulder) move rigidly with either neighbour; they only name a segment that has
#: no other marker.
PART: dict[str, str] = {"C7": "thorax", "T10": "thorax", "CLAV": "thorax", "STRN": "thorax", "RBAC": "thorax"}
ON_JOINT: set[str] = set()
for _s in "LR":
    ON_JOINT |= {f"{_s}{j}" for j in ("KNE", "ANK", "ELB", "WRA", "WRB", "SHO", "AC", "RAD", "ULN", "ANL")}
# Clouthier's cluster set
PART.update({"FHD": "head", "RHD": "head", "BHD": "head", "LHD": "head"})
PART.update({f"LB{v}{h}": "thorax" for v in "UL" for h in "LR"})
PART.update({f"PV{v}{h}": "pelvis" for v in "UL" for h in "LR"})
for _s in "LR":
    PART.update({f"{_s}AC": f"{_s} shoulder", f"{_s}RAD": f"{_s} forearm", f"{_s}ULN": f"{_s} forearm",
                 f"{_s}HAND": f"{_s} hand", f"{_s}ANL": f"{_s} shank"})
    for cluster, part in (("UA", "upper arm"), ("FA", "forearm"), ("TH", "thigh"), ("SH", "shank")):
        PART.update({f"{_s}{cluster}{pd}{ap}": f"{_s} {part}" for pd in "PD" for ap in "AP"})
    PART.update({f"{_s}{m}": f"{_s} foot" for m in ("HEE", "FTB", "FTM", "FTF")})
for _s in "LR":
    PART.update({
        f"{_s}FHD": "head", f"{_s}BHD": "head", f"{_s}SHO": f"{_s} shoulder",
        f"{_s}UPA": f"{_s} upper arm", f"{_s}ELB": f"{_s} upper arm", f"{_s}FRM": f"{_s} forearm",
        f"{_s}WRA": f"{_s} forearm", f"{_s}WRB": f"{_s} forearm", f"{_s}FIN": f"{_s} hand",
        f"{_s}FWT": "pelvis", f"{_s}BWT": "pelvis", f"{_s}THI": f"{_s} thigh", f"{_s}KNE": f"{_s} thigh",
        f"{_s}SHN": f"{_s} shank", f"{_s}ANK": f"{_s} shank", f"{_s}HEE": f"{_s} foot",
        f"{_s}TOE": f"{_s} foot", f"{_s}MT5": f"{_s} foot",
        # Plug-in-Gait names that the CMU set spells otherwise
        f"{_s}ASI": "pelvis", f"{_s}PSI": "pelvis", f"{_s}TIB": f"{_s} shank",
    })
PART["RBAK"] = "thorax"
# numediart's 68-marker set (03_rolling; every label carries a leading "L"): four-marker
# thigh and shank clusters, two on each upper arm and forearm, anatomical landmarks
# (ISB names: epicondyles, styloids, malleoli, metatarsals).
PART.update({f"L{m}": "head" for m in ("RFHD", "LFHD", "LBHD", "RBHD")})
PART.update({f"L{m}": "thorax" for m in ("CLAV", "STRN", "CV7", "TV10")})
for _s in "LR":
    PART.update({
        f"L{_s}AC": f"{_s} shoulder", f"L{_s}UA1": f"{_s} upper arm", f"L{_s}UA2": f"{_s} upper arm",
        f"L{_s}_HLE": f"{_s} upper arm", f"L{_s}_HME": f"{_s} upper arm", f"L{_s}F1": f"{_s} forearm",
        f"L{_s}F2": f"{_s} forearm", f"L{_s}_RSP": f"{_s} forearm", f"L{_s}_USP": f"{_s} forearm",
        f"L{_s}_HM1": f"{_s} hand", f"L{_s}_HL5": f"{_s} hand", f"L{_s}_IPS": "pelvis", f"L{_s}_IAS": "pelvis",
        f"L{_s}_FTC": f"{_s} thigh", f"L{_s}_FLE": f"{_s} thigh", f"L{_s}_FME": f"{_s} thigh",
        f"L{_s}_FAL": f"{_s} shank", f"L{_s}_TAM": f"{_s} shank", f"L{_s}_FCC": f"{_s} foot",
        **{f"L{_s}_TH{k}": f"{_s} thigh" for k in range(1, 5)},
        **{f"L{_s}_SK{k}": f"{_s} shank" for k in range(1, 5)},
        **{f"L{_s}_FM{k}": f"{_s} foot" for k in (1, 2, 5)},
    })
    ON_JOINT |= {f"L{_s}{j}" for j in ("AC", "_HLE", "_HME", "_RSP", "_USP", "_FLE", "_FME", "_FAL", "_TAM")}
PART["LR-SK1"] = "R shank"  # spelled with a hyphen in the file
# biobuddy's lower-limb calibration set: Plug-in-Gait plus spinal processes (S3, S1 on the
# sacrum, S1 at the lumbosacral joint; T6, T1; C2 on the neck), medial epicondyles and
# malleoli (KNEM, ANKM), two more thigh and shank markers each (THIB/THID, TIBF/TIBD),
# navicular and fifth metatarsal head (NAV, TOE5).
PART.update({"S3": "pelvis", "S1": "pelvis", "T6": "thorax", "T1": "thorax", "C2": "thorax"})
ON_JOINT |= {"S1", "C2"}
for _s in "LR":
    PART.update({
        f"{_s}THIB": f"{_s} thigh", f"{_s}THID": f"{_s} thigh", f"{_s}KNEM": f"{_s} thigh",
        f"{_s}TIBF": f"{_s} shank", f"{_s}TIBD": f"{_s} shank", f"{_s}ANKM": f"{_s} shank",
        f"{_s}NAV": f"{_s} foot", f"{_s}TOE5": f"{_s} foot",
    })
    ON_JOINT |= {f"{_s}KNEM", f"{_s}ANKM"}

ADJACENT: set[frozenset[str]] = {frozenset(("pelvis", "thorax")), frozenset(("thorax", "head"))}
for _s in "LR":
    ADJACENT |= {frozenset(p) for p in (
        ("thorax", f"{_s} shoulder"), (f"{_s} shoulder", f"{_s} upper arm"), ("thorax", f"{_s} upper arm"),
        (f"{_s} upper arm", f"{_s} forearm"), (f"{_s} forearm", f"{_s} hand"), ("pelvis", f"{_s} thigh"),
        (f"{_s} thigh", f"{_s} shank"), (f"{_s} shank", f"{_s} foot"),
    )}


def segment_parts(labels, marker_segment) -> list[str | None]:
    """Body part of each segment: the majority of its off-joint markers (else of all); a tie
    goes to the part more of all its markers (those on joints too) name, then alphabetically.
    (numediart 85_12's group of shin, ankle and heel markers, one off-joint marker each of
    shank and foot, is the shank: its ankle marker counts for the shank.)"""
    names = [lab.split(":")[-1] for lab in labels]
    parts = []
    for s in range(int(np.max(marker_segment)) + 1):
        mine = [n for n, g in zip(names, marker_segment) if g == s and n in PART]
        every = [PART[n] for n in mine]
        votes = [PART[n] for n in mine if n not in ON_JOINT] or every
        parts.append(max(sorted(set(votes)), key=lambda p: (votes.count(p), every.count(p))) if votes else None)
    return parts


def implausible_edges(labels, marker_segment, edges) -> list[tuple[str, str]]:
    """Tree edges joining body parts that are not adjacent in a human skeleton."""
    parts = segment_parts(labels, marker_segment)
    bad = []
    for a, b in np.asarray(edges).reshape(-1, 2).tolist():
        pa, pb = parts[a], parts[b]
        if pa is not None and pb is not None and pa != pb and frozenset((pa, pb)) not in ADJACENT:
            bad.append((pa, pb))
    return bad


def asf_bone_lengths(path: Path) -> dict[str, float]:
    """Bone name -> length in metres from an Acclaim .asf file (``:units length`` aware:
    a length ``L`` is ``L / unit`` inches)."""
    unit = 1.0
    lengths: dict[str, float] = {}
    name = None
    section = None
    for line in Path(path).read_text().splitlines():
        words = line.split()
        if not words:
            continue
        if words[0].startswith(":"):
            section = words[0]
            continue
        if section == ":units" and words[0] == "length":
            unit = float(words[1])
        elif section == ":bonedata":
            if words[0] == "name":
                name = words[1]
            elif words[0] == "length" and name is not None:
                lengths[name] = float(words[1]) / unit * 0.0254
    return lengths


def bone_index_by_part(result) -> dict[str, int]:
    """Index into ``result.skeleton.bones`` of each limb bone, named by its body parts:
    e.g. ``"L thigh"`` is the bone between the pelvis-thigh and thigh-shank joints."""
    sk = result.skeleton
    parts = segment_parts(result.trial.labels, result.segmentation.marker_segment)
    neighbours = {"thigh": ("pelvis", "shank"), "shank": ("thigh", "foot"),
                  "upper arm": (("thorax", "shoulder"), "forearm"), "forearm": ("upper arm", "hand")}
    out = {}
    for b, (i, j) in enumerate(np.asarray(sk.bones).tolist()):
        seg = int(sk.bone_segment[b])
        part = parts[seg]
        if part is None or part[2:] not in neighbours:
            continue
        side = part[0]
        ends = set()
        for joint in (i, j):
            other = [int(v) for v in sk.edges[joint] if int(v) != seg][0]
            ends.add((parts[other] or "").replace(f"{side} ", ""))
        proximal, distal = neighbours[part[2:]]
        proximal = proximal if isinstance(proximal, tuple) else (proximal,)
        if ends & set(proximal) and distal in ends:
            out[part] = b
    return out


def misplaced_markers(labels, marker_segment, distance_std=None, rigid_limit=None) -> list[tuple[str, str]]:
    """Markers grouped with a body part they are not on: ``(marker, segment's part)``.
    A marker on a joint may sit with either body part of that joint. Given the
    segmentation's ``distance_std`` and ``rigid_limit``, a marker whose median distance
    std to the markers of the segment's part is within the limit is not counted either:
    the recording does not move the two parts apart (a wrist it never bends)."""
    names = [lab.split(":")[-1] for lab in labels]
    parts = segment_parts(labels, marker_segment)
    seg = np.asarray(marker_segment)
    bad = []
    for i, (n, g) in enumerate(zip(names, seg.tolist())):
        if g < 0 or n not in PART or parts[g] is None or PART[n] == parts[g]:
            continue
        if n in ON_JOINT and frozenset((PART[n], parts[g])) in ADJACENT:
            continue
        if distance_std is not None:
            own = [j for j, (m, h) in enumerate(zip(names, seg.tolist())) if h == g and PART.get(m) == parts[g]]
            if own and np.nanmedian(np.asarray(distance_std)[i, own]) <= rigid_limit:
                continue
        bad.append((n, parts[g]))
    return bad
