"""Zero clicks: the cardia and pylorus found automatically, from a multi-label segmentation or from the stomach gas.

``find_points(ct, labels=None, names=None)`` returns an :class:`AutoPoints`: the cardia and pylorus (LPS mm), a
confidence in [0, 1] for each and what they were found from (the labels used, or the gas evidence).

* With a multi-label segmentation on the CT's grid (TotalSegmentator's ``total`` task, v2 or v1 numbering,
  recognised by number; a Slicer segmentation by segment name or terminology code, passed as ``names``):
  the cardia lies where the oesophagus label meets the stomach label, the pylorus where the stomach meets the
  duodenum, each moved into the stomach (to the gas when the lumen holds some) and snapped onto the stomach
  label as the front end snaps points.
* Without one (a gas-distended CT): the stomach gas is the large gas region inside the body that is neither
  outside air (it touches the volume's sides), lung (it reaches the top face, is lung-dense or too large) nor
  bowel (lower, smaller, to the right); the pylorus is at the far end of the gas from the fundus top, where the
  lumen first widens to the pyloric canal (``PYLORIC_CANAL_MIN_RADIUS_MM``; a thin open duodenum before it is
  passed over); the cardia on the medial side of the fundus dome where the oesophagus leaves (an open gas tube, else
  the site whose probe rays meet the most oesophageal wall density), ``CARDIA_DEPTH_MM`` inside the gas. The
  cardia is unsure (confidence below ``CONFIDENCE_THRESHOLD``) when that tube is faint or a rival site on the dome
  scores as well; the pylorus when no canal-wide lumen comes within ``PYLORUS_MAX_TAIL_MM`` of the far end.

Coordinates are LPS mm; messages name points in RAS (as Slicer shows them).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .errors import AnatomyError, InputError
from .geometry import Volume, lps_to_ras
from .preprocessing import MAX_STOMACH_ML, bounding_box, distance_mm, fluid_below_level, nearest_true

__all__ = ["AutoPoints", "CLASS_MAPS", "TERMINOLOGY", "CONFIDENCE_THRESHOLD", "CARDIA_DEPTH_MM", "PYLORUS_DEPTH_MM",
           "recognise_labels", "stomach_label", "points_from_labels", "find_stomach_gas", "points_from_gas",
           "find_points", "labels_on_grid", "auto_points_or_refuse"]

#: TotalSegmentator's ``total`` task: the organs used here, by class number (v2 "total" and v1 "total_v1").
CLASS_MAPS = {
    "total": {"spleen": 1, "liver": 5, "stomach": 6, "pancreas": 7, "lung_upper_lobe_left": 10,
              "lung_lower_lobe_left": 11, "lung_upper_lobe_right": 12, "lung_middle_lobe_right": 13,
              "lung_lower_lobe_right": 14, "esophagus": 15, "small_bowel": 18, "duodenum": 19, "colon": 20},
    "total_v1": {"spleen": 1, "liver": 5, "stomach": 6, "pancreas": 10, "lung_upper_lobe_left": 13,
                 "lung_lower_lobe_left": 14, "lung_upper_lobe_right": 15, "lung_middle_lobe_right": 16,
                 "lung_lower_lobe_right": 17, "esophagus": 42, "small_bowel": 55, "duodenum": 56, "colon": 57},
}
#: Highest class number of each convention (a label above 104 can only be v2).
CLASS_MAP_MAX = {"total": 117, "total_v1": 104}
#: Segment names and SNOMED CT codes (Slicer terminology) that name each organ.
TERMINOLOGY = {"stomach": ("stomach", "69695003"), "esophagus": ("esophagus", "oesophagus", "32849002"),
               "duodenum": ("duodenum", "38848004")}
#: Below this confidence the command line refuses the points and the Slicer module asks the user to check them.
CONFIDENCE_THRESHOLD = 0.5
#: How far (mm) inside the lumen the points are put: the cardia past the opening, the pylorus before it.
CARDIA_DEPTH_MM = 5.0
PYLORUS_DEPTH_MM = 3.0
#: The thickest stomach wall (mm) looked through for the gas from a tube label's contact.
MAX_WALL_MM = 10.0
#: How far (mm) back from the far end of the gas the pylorus is looked for past a thin (duodenal) tail.
PYLORUS_MAX_WALK_MM = 8.0
#: Weight of the usual cardia direction against the tissue-tube evidence (score per unit of 1 - cos angle).
CARDIA_PRIOR_WEIGHT = 2.0
#: Candidates scoring within this of the best share the vote for the cardia (score units: tissue fraction).
CARDIA_SCORE_BAND = 0.3
#: Oesophageal wall density (HU, on the CT smoothed by OESOPHAGUS_SMOOTH_MM): muscle-like, above fat and water,
#: below unenhanced liver.
OESOPHAGUS_HU = (15.0, 52.0)
OESOPHAGUS_SMOOTH_MM = 1.5
#: Half-angle (degrees) of the cone of probe rays around the usual oesophageal direction.
CARDIA_CONE_DEG = 20.0
#: An open oesophageal lumen on a probe ray: darker than fat (HU, smoothed CT) continuously from the stomach gas
#: for at least OPEN_LUMEN_MIN_MM (a wall and fat cross over within a few mm elsewhere).
OPEN_LUMEN_HU = -110.0
OPEN_LUMEN_MIN_MM = 8.0
#: A candidate this far (mm) from the chosen cardia counts as a rival site when judging how sure the choice is.
CARDIA_RIVAL_MM = 12.0
#: The cardia's support: the share of tissue along its probe plus this times its score's lead over the best rival site.
CARDIA_MARGIN_WEIGHT = 2.0
#: A thin tail longer than this (mm) before the canal-wide lumen: the far end is not a pylorus we recognise.
PYLORUS_MAX_TAIL_MM = 30.0
#: A gas tube thinner than this (equivalent lumen radius, mm) at the far end of the gas is the duodenum (open over its
#: first centimetres), not the pyloric canal: the pylorus is where the lumen first widens past it.
PYLORIC_CANAL_MIN_RADIUS_MM = 3.5
#: Width (mm) of the geodesic distance bins in which the lumen's cross-section is measured from its far end.
PROFILE_BIN_MM = 2.0
#: Weight of the distance to the patient's right (mm per mm) added to the geodesic length when picking the far end.
RIGHTWARD_WEIGHT = 1.0


@dataclass
class AutoPoints:
    """Automatically found cardia and pylorus (LPS mm), a confidence in [0, 1] each, and what they came from."""

    cardia_lps: np.ndarray
    pylorus_lps: np.ndarray
    cardia_confidence: float
    pylorus_confidence: float
    source: str                                   # "segmentation" or "gas"
    labels: dict = field(default_factory=dict)    # organ -> label value used (segmentation)
    convention: str | None = None                 # "total", "total_v1", "names" or "single label"
    evidence: list = field(default_factory=list)  # one sentence per finding

    @property
    def confidence(self) -> float:
        """The lower of the two points' confidences."""
        return float(min(self.cardia_confidence, self.pylorus_confidence))

    @property
    def confident(self) -> bool:
        """True when both points reach ``CONFIDENCE_THRESHOLD``."""
        return self.confidence >= CONFIDENCE_THRESHOLD

    def to_dict(self) -> dict:
        """The report's ``auto_points`` section (points in LPS and RAS mm)."""
        c, p = np.asarray(self.cardia_lps, float), np.asarray(self.pylorus_lps, float)
        return {"source": self.source, "convention": self.convention, "labels": dict(self.labels),
                "cardia_lps": c.tolist(), "pylorus_lps": p.tolist(), "cardia_ras": lps_to_ras(c).tolist(),
                "pylorus_ras": lps_to_ras(p).tolist(), "cardia_confidence": float(self.cardia_confidence),
                "pylorus_confidence": float(self.pylorus_confidence), "threshold": CONFIDENCE_THRESHOLD,
                "evidence": list(self.evidence)}

    def guesses_ras_text(self) -> str:
        """The two points as ``--cardia R,A,S --pylorus R,A,S`` text (RAS mm, 1 decimal)."""
        def t(p):
            return ",".join(f"{v:.1f}" for v in lps_to_ras(np.asarray(p, float)))
        return f"--cardia {t(self.cardia_lps)} --pylorus {t(self.pylorus_lps)}"


# ---------------------------------------------------------------------------------------------- recognition
def _organ_of_name(name: str) -> str | None:
    """The organ (stomach, esophagus, duodenum) a segment name or terminology string names, else None."""
    t = str(name).lower().replace("-", "_").replace(" ", "_")
    for organ, words in TERMINOLOGY.items():
        if any(w in t for w in words):
            return organ
    return None


def _touching(labels: np.ndarray, a: int, b: int, reach_vox: int = 2) -> bool:
    """True when label ``b`` lies within ``reach_vox`` voxels of label ``a`` (on a's bounding box)."""
    m = labels == a
    if not m.any():
        return False
    lo, hi = bounding_box(m, (reach_vox + 1,) * 3)
    sub = labels[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    grown = ndimage.binary_dilation(sub == a, iterations=reach_vox)
    return bool(np.any(grown & (sub == b)))


def recognise_labels(labels: np.ndarray, names: dict | None = None, convention: str | None = None) -> dict:
    """Which label values are the stomach, oesophagus and duodenum in a label array; a dict with the evidence.

    ``names``: {label value: segment name or terminology text} (a Slicer segmentation); else the values are
    read as TotalSegmentator's ``total`` class map, the v2 numbering (``"total"``) or v1 (``"total_v1"``), the
    one whose oesophagus and duodenum touch its stomach (or ``convention`` if given). A label array with a
    single value is taken as the stomach. Returns {"stomach", "esophagus", "duodenum" (values or None),
    "convention", "evidence" (list of str)}; InputError when no stomach label can be recognised.
    """
    labels = np.asarray(labels)
    present = [int(v) for v in np.unique(labels) if v != 0]
    if not present:
        raise InputError("the segmentation is empty; give a label volume with a stomach label")
    if names:
        found = {"stomach": None, "esophagus": None, "duodenum": None}
        for value, name in names.items():
            organ = _organ_of_name(name)
            if organ and found[organ] is None and int(value) in present:
                found[organ] = int(value)
        if found["stomach"] is None:
            raise InputError("no segment is named stomach (or has the SNOMED code 69695003) among "
                             f"{', '.join(repr(str(n)) for n in names.values())}; name the stomach segment 'stomach'")
        ev = [f"{o} = label {v} (by segment name)" for o, v in found.items() if v is not None]
        return {**found, "convention": "names", "evidence": ev}
    if len(present) == 1:
        return {"stomach": present[0], "esophagus": None, "duodenum": None, "convention": "single label",
                "evidence": [f"the segmentation has one label ({present[0]}), taken as the stomach"]}
    choices = [convention] if convention else list(CLASS_MAPS)
    for c in choices:
        if c not in CLASS_MAPS:
            raise InputError(f"unknown class map {c!r}; choose one of {', '.join(CLASS_MAPS)}")
    best, best_score = None, -1.0
    for c in choices:
        cmap = CLASS_MAPS[c]
        if cmap["stomach"] not in present or (max(present) > CLASS_MAP_MAX[c] and not convention):
            continue
        score = 1.0
        for organ in ("esophagus", "duodenum"):
            if cmap[organ] in present:
                score += 0.5 + (_touching(labels, cmap["stomach"], cmap[organ]) if not convention else 0.0)
        if score > best_score:
            best, best_score = c, score
    if best is None:
        raise InputError(f"no TotalSegmentator stomach label (6) among the labels {present[:12]}"
                         f"{' ...' if len(present) > 12 else ''}; give the stomach label with --mask-label")
    cmap = CLASS_MAPS[best]
    found = {o: (cmap[o] if cmap[o] in present else None) for o in ("stomach", "esophagus", "duodenum")}
    ev = [f"TotalSegmentator '{best}' class map" + (" (given)" if convention else f" (match score {best_score:g})")]
    ev += [f"{o} = label {v}" for o, v in found.items() if v is not None]
    ev += [f"no {o} label ({cmap[o]})" for o, v in found.items() if v is None]
    return {**found, "convention": best, "evidence": ev}


def stomach_label(labels: np.ndarray, names: dict | None = None, convention: str | None = None) -> int:
    """The stomach's label value in a multi-label array (see :func:`recognise_labels`); InputError if none."""
    return int(recognise_labels(labels, names, convention)["stomach"])


# ---------------------------------------------------------------------------------------------- geometry helpers
def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else v


def _inside_along(mask_vol: Volume, start, direction, depth_mm: float, step_mm: float = 0.5) -> np.ndarray:
    """The point ``depth_mm`` from ``start`` along ``direction`` (LPS mm), pulled back while it leaves the mask."""
    d = _unit(direction)
    for t in np.arange(depth_mm, -step_mm, -step_mm):
        p = np.asarray(start, float) + t * d
        if mask_vol.sample(p[None], order=0, cval=0)[0] > 0.5:
            return p
    return np.asarray(start, float)


def _inward_normal(mask_vol: Volume, p, sigma_mm: float = 3.0) -> np.ndarray:
    """Unit vector (LPS) into the mask at LPS point p: the gradient of the mask smoothed by sigma_mm."""
    g = ndimage.gaussian_filter(mask_vol.array.astype(np.float32), sigma_mm / mask_vol.spacing[::-1])
    gv = mask_vol.with_array(g)
    h = 1.5
    grad = np.array([gv.sample((p + h * e)[None])[0] - gv.sample((p - h * e)[None])[0] for e in np.eye(3)])
    return _unit(grad)


# ---------------------------------------------------------------------------------------------- from a segmentation
def _opening(ct_c: Volume, stomach: np.ndarray, tube: np.ndarray, depth_mm: float, threshold_hu: float,
             name: str):
    """Where a tube label meets the stomach label on a crop: (LPS point inside the stomach, confidence, evidence)."""
    if not tube.any():
        return None, 0.0, f"no {name} voxel near the stomach"
    d_tube = distance_mm(~tube, ct_c.spacing)          # mm from each voxel to the tube
    reach = 1.5 * float(ct_c.spacing.max()) + 0.5
    gap = float(d_tube[stomach].min())
    if gap > 15.0:
        return None, 0.0, f"the {name} label comes no closer than {gap:.0f} mm to the stomach"
    contact = stomach & (d_tube <= max(reach, gap + float(ct_c.spacing.max())))
    o = ct_c.voxel_lps(contact).mean(0)
    s_vol = ct_c.with_array(stomach.astype(np.uint8))
    n_in = _inward_normal(s_vol, o)
    near_tube = ct_c.voxel_lps(tube & (distance_mm(~contact, ct_c.spacing) <= 15.0))
    t_dir = _unit(o - near_tube.mean(0)) if len(near_tube) else n_in
    direction = _unit(2.0 * n_in + t_dir)
    # the lumen side: past the wall into the gas when the stomach holds gas there, else a typical wall + depth
    ts = np.arange(0.0, 25.0, 0.5)
    ray = o[None] + ts[:, None] * direction[None]
    hu = ct_c.sample(ray, order=1, cval=0.0)
    ins = s_vol.sample(ray, order=0, cval=0) > 0.5
    gas = np.nonzero((hu < threshold_hu) & ins & (ts <= MAX_WALL_MM))[0]   # gas deeper is past retained fluid
    conf = 0.95 if gap <= reach else max(0.6, 0.95 - 0.03 * gap)
    if len(gas):
        depth = ts[gas[0]] + depth_mm
        how = f"{ts[gas[0]]:.0f} mm through the wall to the gas, then {depth_mm:g} mm"
    else:
        depth = 4.0 + depth_mm
        how = f"no gas on the lumen side: {depth:g} mm into the label"
        conf *= 0.9
    p = _inside_along(s_vol, o, direction, depth)
    ev = (f"{name}: {int(contact.sum())} stomach voxels within {max(reach, gap):.1f} mm of the {name} label; "
          f"point {how} inward")
    return p, conf, ev


def points_from_labels(ct: Volume, labels: np.ndarray, names: dict | None = None, convention: str | None = None,
                       threshold_hu: float = -500.0, max_snap_mm: float = 20.0) -> AutoPoints:
    """Cardia and pylorus (LPS mm) from a multi-label segmentation on ``ct``'s grid (see :func:`recognise_labels`).

    The cardia is put where the oesophagus label meets the stomach label, the pylorus where the stomach meets the
    duodenum, each moved inward (past the wall to the gas, then ``CARDIA_DEPTH_MM`` / ``PYLORUS_DEPTH_MM``) and
    snapped onto the stomach label within ``max_snap_mm``; a missing tube label falls back to the stomach
    label's shape (low confidence).
    """
    labels = np.asarray(labels)
    if labels.shape != ct.array.shape:
        raise InputError(f"the segmentation has shape {labels.shape}, the CT {ct.array.shape}: resample it onto "
                         "the CT grid (io.read_label_volume does)")
    rec = recognise_labels(labels, names, convention)
    stomach_full = labels == rec["stomach"]
    lo, hi = bounding_box(stomach_full, tuple(int(np.ceil(25.0 / s)) for s in ct.spacing))
    ct_c = ct.crop(lo, hi)
    sub = labels[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    stomach = sub == rec["stomach"]
    evidence = list(rec["evidence"])
    found = {}
    for point, organ, depth in (("cardia", "esophagus", CARDIA_DEPTH_MM), ("pylorus", "duodenum", PYLORUS_DEPTH_MM)):
        tube = sub == rec[organ] if rec[organ] is not None else np.zeros_like(stomach)
        p, conf, ev = _opening(ct_c, stomach, tube, depth, threshold_hu, organ)
        evidence.append(ev)
        found[point] = (p, conf)
    if found["cardia"][0] is None or found["pylorus"][0] is None:
        shape = _shape_points(ct_c, stomach, gas=False)
        evidence += shape["evidence"]
        for point in ("cardia", "pylorus"):
            if found[point][0] is None:
                found[point] = (shape[point], 0.35 * shape[point + "_confidence"])
                evidence.append(f"{point} from the stomach label's shape (no usable tube label): low confidence")
    pts = {}
    for point, (p, conf) in found.items():
        snapped = nearest_true(stomach_full, ct, p, max_snap_mm)
        pts[point] = snapped if snapped is not None else p
    used = {o: rec[o] for o in ("stomach", "esophagus", "duodenum") if rec[o] is not None}
    return AutoPoints(pts["cardia"], pts["pylorus"], float(found["cardia"][1]), float(found["pylorus"][1]),
                      "segmentation", used, rec["convention"], evidence)


# ---------------------------------------------------------------------------------------------- from the shape
def _geodesic(region: np.ndarray, spacing, source: int):
    """Geodesic distances (mm) inside ``region`` (26-connected voxel graph) from node ``source``; (dist, pred, ids)."""
    from scipy import sparse
    from scipy.sparse.csgraph import dijkstra

    ids = -np.ones(region.shape, np.int64)
    kk, jj, ii = np.nonzero(region)
    ids[kk, jj, ii] = np.arange(len(kk))
    sp = np.asarray(spacing, float)[::-1]                  # (k, j, i) mm
    rows, cols, wts = [], [], []
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]
    K, J, I = region.shape
    for a, b, c in offsets:
        src = ids[max(0, -a):K - max(0, a), max(0, -b):J - max(0, b), max(0, -c):I - max(0, c)]
        dst = ids[max(0, a):K - max(0, -a) or None, max(0, b):J - max(0, -b) or None, max(0, c):I - max(0, -c) or None]
        ok = (src >= 0) & (dst >= 0)
        rows.append(src[ok])
        cols.append(dst[ok])
        wts.append(np.full(int(ok.sum()), float(np.linalg.norm(np.array([a, b, c]) * sp))))
    n = len(kk)
    g = sparse.csr_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    dist, pred = dijkstra(g, directed=False, indices=source, return_predecessors=True)
    return dist, pred, (kk, jj, ii)


def _oesophagus_probe(ct_c: Volume, r_vol: Volume, cand: np.ndarray, centre: np.ndarray, d0: np.ndarray):
    """The medial dome point (LPS mm) where the oesophagus leaves superomedially: (point, outward normal, tissue
    share along its probe, lead of its score over the best candidate more than ``CARDIA_RIVAL_MM`` away).

    Each candidate surface point is scored by the share of its probe (6-26 mm out along a ray leaving it up and
    medially, the best of a ``CARDIA_CONE_DEG`` cone of rays) that is oesophagus: muscle-density soft tissue
    (``OESOPHAGUS_HU`` on the CT smoothed by ``OESOPHAGUS_SMOOTH_MM``: the wall, not fat, not the denser liver) or
    an open lumen (darker than fat continuously from the gas for ``OPEN_LUMEN_MIN_MM``), less a penalty for lying
    far from the usual direction ``d0`` from the dome centre. The point is the candidate nearest the score-weighted
    centroid of all candidates within ``CARDIA_SCORE_BAND`` of the best (one noisy ray does not decide); without a
    tube the support point toward ``d0`` wins.
    """
    g = ndimage.gaussian_filter(r_vol.array.astype(np.float32), 2.0 / r_vol.spacing[::-1])
    gv = r_vol.with_array(g)
    h = 1.5
    grad = np.stack([gv.sample(cand + h * e) - gv.sample(cand - h * e) for e in np.eye(3)], 1)
    n_out = -grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    u = np.array([-0.55, 0.2, 1.0])[None] + 0.6 * n_out
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    smooth = ct_c.with_array(ndimage.gaussian_filter(ct_c.array.astype(np.float32),
                                                     OESOPHAGUS_SMOOTH_MM / ct_c.spacing[::-1]))
    step = 2.0
    ts = np.arange(0.0, 26.0, step)
    probe = ts >= 6.0
    tissue = np.zeros(len(cand))
    # the ray and a cone of rays around it (the tube's course varies): the best one counts
    a = np.cross(u, [0.0, 1.0, 0.0])
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-9)
    b = np.cross(u, a)
    tilt = np.tan(np.radians(CARDIA_CONE_DEG))
    for da, db in [(0.0, 0.0)] + [(np.cos(t), np.sin(t)) for t in np.linspace(0, 2 * np.pi, 6, endpoint=False)]:
        ud = u + tilt * (da * a + db * b)
        ud /= np.linalg.norm(ud, axis=1, keepdims=True)
        ray = cand[:, None, :] + ts[None, :, None] * ud[:, None, :]
        hu = smooth.sample(ray.reshape(-1, 3), order=1, cval=-1024.0).reshape(len(cand), len(ts))
        # an open oesophagus: the ray stays darker than fat from the gas on, past where a wall would be
        lumen = np.cumprod(hu < OPEN_LUMEN_HU, axis=1).astype(bool)
        lumen &= (lumen.sum(1) * step >= OPEN_LUMEN_MIN_MM)[:, None]
        tube = ((hu > OESOPHAGUS_HU[0]) & (hu < OESOPHAGUS_HU[1])) | lumen
        tissue = np.maximum(tissue, tube[:, probe].mean(1))
    v = cand - centre
    cosang = (v @ d0) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
    support = v @ d0
    level = n_out[:, 1] > 0.6          # a flat air-fluid level faces posterior (supine): no opening there
    score = tissue - CARDIA_PRIOR_WEIGHT * (1.0 - cosang) + 0.01 * (support - support.max()) - 10.0 * level
    top = np.nonzero(score >= score.max() - CARDIA_SCORE_BAND)[0]
    w = np.exp((score[top] - score.max()) / CARDIA_SCORE_BAND)
    c = (cand[top] * w[:, None]).sum(0) / w.sum()
    best = int(top[np.argmin(np.linalg.norm(cand[top] - c, axis=1))])
    # ambiguity: how much better the vote's winner scores than the best candidate elsewhere on the dome
    far = np.linalg.norm(cand - cand[best], axis=1) > CARDIA_RIVAL_MM
    margin = float(score[best] - score[far].max()) if far.any() else 1.0
    return cand[best], n_out[best], float(tissue[best]), margin


def _thin_tube_base(ct_c: Volume, thin: np.ndarray, opened: np.ndarray, centre: np.ndarray, radius: float):
    """Where a thin gas tube (an open oesophagus) leaves the dome superomedially: LPS point (mm) or None."""
    lab, n = ndimage.label(thin)
    best, best_len = None, 6.0
    for i in range(1, n + 1):
        comp = lab == i
        pts = ct_c.voxel_lps(comp)
        if len(pts) < 3:
            continue
        base_mask = opened & ndimage.binary_dilation(comp, iterations=1)
        if not base_mask.any():
            continue
        base = ct_c.voxel_lps(base_mask).mean(0)
        far = pts[np.argmax(np.linalg.norm(pts - base, axis=1))]
        length = float(np.linalg.norm(far - base))
        v = base - centre
        medial = v[0] < -0.3 * radius and abs(v[2]) < 1.2 * radius and np.linalg.norm(v) < 1.6 * radius
        rising = far[2] > base[2] + 0.3 * length
        if medial and rising and length > best_len:
            best, best_len = base, length
    return best


def _pylorus_past_tail(region: np.ndarray, ct_c: Volume, P: np.ndarray, tip: int):
    """The pylorus (LPS mm) from the far end ``tip`` of a lumen region: (point or None, thin tail length mm).

    The lumen's cross-section is measured in ``PROFILE_BIN_MM`` bins of geodesic distance from the tip (equivalent
    radius sqrt(area / pi)); an open duodenum is a thin tail there, the pyloric canal wider. The pylorus is the
    middle of the first bin, followed by a second, whose radius reaches ``PYLORIC_CANAL_MIN_RADIUS_MM``: the
    canal's end (no tail: a bin from the tip). None when the region stays thinner over its first 40 mm.
    """
    dt, _, _ = _geodesic(region, ct_c.spacing, tip)
    bw = PROFILE_BIN_MM
    nb = int(round(40.0 / bw))
    ok = np.isfinite(dt) & (dt < nb * bw)
    b = (dt[ok] / bw).astype(int)
    area = np.bincount(b, minlength=nb)[:nb] * float(np.prod(ct_c.spacing)) / bw
    wide = np.sqrt(area / np.pi) >= PYLORIC_CANAL_MIN_RADIUS_MM
    first = np.nonzero(wide[:-1] & wide[1:])[0]
    if not len(first):
        return None, 40.0
    i = int(first[0])
    sel = np.nonzero(ok)[0][b == i]
    return P[sel].mean(0), float(i * bw)


def _shape_points(ct_c: Volume, region: np.ndarray, gas: bool = True) -> dict:
    """Cardia and pylorus guesses (LPS mm) from the shape of a stomach region (gas or label) on a crop.

    The fundus top is the region's most superior thick voxel; the pylorus lies at the far end of the region from it,
    where the lumen widens to the pyloric canal (:func:`_pylorus_past_tail`; else the first voxel back along the
    geodesic at least ``PYLORUS_DEPTH_MM`` from the region's edge); the cardia on the medial side of the fundus dome
    where the oesophagus leaves (:func:`_oesophagus_probe`, or the base of a thin gas tube), ``CARDIA_DEPTH_MM``
    inside.
    """
    edt = distance_mm(region, ct_c.spacing)
    kk, jj, ii = np.nonzero(region)
    P = ct_c.index_to_lps(np.stack([ii, jj, kk], 1).astype(float))
    e = edt[kk, jj, ii]
    vox = float(ct_c.spacing.max())
    thick = e >= min(PYLORUS_DEPTH_MM, 1.5 * vox)
    cand = np.nonzero(thick)[0] if thick.any() else np.arange(len(P))
    top = int(cand[np.argmax(P[cand, 2])])
    dist, pred, _ = _geodesic(region, ct_c.spacing, top)
    dist = np.where(np.isfinite(dist), dist, -1.0)
    # the far end toward the patient's right (the antrum turns right to the pylorus), not the greater curvature's
    # lowest point, which can lie as far along the region from the top
    tip = int(np.argmax(np.where(dist >= 0, dist + RIGHTWARD_WEIGHT * (P[top, 0] - P[:, 0]), -np.inf)))
    path = [tip]
    while path[-1] != top and pred[path[-1]] >= 0 and len(path) < 100000:
        path.append(int(pred[path[-1]]))
    path = np.array(path)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P[path], axis=0), axis=1))])
    # past a thin (open duodenal) tail to where the lumen widens to the pyloric canal
    pyl, tail_mm = _pylorus_past_tail(region, ct_c, P, tip)
    if pyl is None:  # no canal-wide lumen near the far end: the first deep point back along the path
        deep = np.nonzero((e[path] >= PYLORUS_DEPTH_MM) & (arc <= PYLORUS_MAX_WALK_MM))[0]
        pyl = P[path[deep[0]]] if len(deep) else P[path[int(np.searchsorted(arc, PYLORUS_DEPTH_MM))]]
    # fundus dome: the widest point near the top; the cardia on its medial side
    near = np.nonzero((dist >= 0) & (dist <= 55.0))[0]
    radius = float(e[near].max())
    centre = P[near[e[near] >= 0.9 * radius]].mean(0)   # the middle of the dome's medial plateau
    near = np.nonzero((dist >= 0) & (dist <= 80.0))[0]
    d0 = _unit([-1.0, 0.17, 0.13])
    # candidates: the medial surface of the region opened by a ball (not a thin oesophageal gas tube)
    r_open = 2.0 * vox
    opened = distance_mm(~(edt >= r_open), ct_c.spacing) <= r_open + 0.5 * vox
    rel = np.linalg.norm(P[near] - centre, axis=1)
    band = near[(P[near, 2] >= centre[2] - 0.35 * radius) & (P[near, 2] <= centre[2] + 0.8 * radius)
                & (rel <= 1.7 * radius) & (e[near] <= 1.05 * vox + 1e-6)
                & ((P[near] - centre) @ d0 > 0.0) & opened[kk[near], jj[near], ii[near]]]
    if not len(band):
        band = near
    r_vol = ct_c.with_array(region.astype(np.uint8))
    s, n_out, tube, margin = _oesophagus_probe(ct_c, r_vol, P[band], centre, d0)
    gas_tube = _thin_tube_base(ct_c, region & ~opened, opened, centre, radius)
    if gas_tube is not None:
        s, n_out = gas_tube, _unit(gas_tube - centre)
    cardia = _inside_along(r_vol, s, -n_out, CARDIA_DEPTH_MM - 0.5 * vox)
    length = float(dist[tip])
    # the cardia is surest where an open oesophagus shows as a thin gas tube, next where a tissue tube leaves
    # clearly: much of the probe in tissue and no rival site on the dome scoring as well (a faint or rivalled tube:
    # unsure, below CONFIDENCE_THRESHOLD when tissue share + 2 x lead < about 0.45)
    support = tube + CARDIA_MARGIN_WEIGHT * margin
    c_conf = 0.9 if gas_tube is not None else 0.3 + 0.45 * float(np.clip(support, 0.0, 1.2))
    weak = gas_tube is None and c_conf < CONFIDENCE_THRESHOLD
    p_conf = 0.8 if tail_mm <= PYLORUS_MAX_TAIL_MM else 0.4
    ev = [f"{'gas' if gas else 'label'} shape: fundus top RAS {np.round(lps_to_ras(P[top]), 1).tolist()}, dome "
          f"radius {radius:.0f} mm, far end {length:.0f} mm along the {'gas' if gas else 'label'}",
          "cardia: " + ("the base of a thin gas tube leaving the dome superomedially (open oesophagus)"
                        if gas_tube is not None else
                        f"the medial dome where soft tissue leaves superomedially ({100 * tube:.0f} % tissue "
                        f"along the probe, {margin:+.2f} ahead of the best rival site)"),
          "pylorus: " + (f"where the lumen widens to the pyloric canal, {tail_mm:.0f} mm from the far end"
                         + (" (past a thin duodenal gas tail)" if tail_mm > 2 * PROFILE_BIN_MM else "")
                         if tail_mm <= PYLORUS_MAX_TAIL_MM else
                         f"no canal-wide lumen within {tail_mm:.0f} mm of the far end: unsure")]
    if weak:
        ev.append("the oesophageal tissue tube is faint and another site on the dome scores as well: unsure of the "
                  "cardia")
    if length < 80.0:
        c_conf, p_conf = c_conf * 0.5, p_conf * 0.5
        ev.append(f"the region is only {length:.0f} mm long (a stomach is over 80 mm): unsure")
    if pyl[0] > centre[0] - 15.0:
        p_conf *= 0.5
        ev.append("the far end does not lie to the patient's right of the fundus: unsure of the pylorus")
    if radius < 12.0:
        c_conf *= 0.5
        ev.append(f"no fundus dome (widest {radius:.0f} mm): unsure of the cardia")
    return {"cardia": cardia, "pylorus": pyl, "cardia_confidence": c_conf, "pylorus_confidence": p_conf,
            "evidence": ev}


# ---------------------------------------------------------------------------------------------- from the gas
#: Gas regions smaller than this (mL) are not taken for a distended stomach.
MIN_GAS_ML = 20.0


def _superior_face(ct: Volume) -> tuple[int, bool]:
    """The array axis (0=k, 1=j, 2=i) closest to superior and whether its high index end is the superior one."""
    si_ijk = int(np.argmax(np.abs(ct.direction[2, :])))
    return 2 - si_ijk, bool(ct.direction[2, si_ijk] > 0)


def find_stomach_gas(ct: Volume, threshold_hu: float = -500.0) -> tuple[np.ndarray, dict]:
    """The stomach gas of a CT (HU): a bool mask on its grid and an info dict (mL, candidates, evidence).

    Gas is below ``threshold_hu`` (6-connected regions). Left out: regions touching the volume's sides (outside
    air, bowel running out of the volume), over ``MAX_STOMACH_ML``, lung (mean over -910 HU and large or reaching
    the top face) and regions under ``MIN_GAS_ML``. The rest are scored by volume, height (the stomach lies under
    the left hemidiaphragm) and side (the patient's left); AnatomyError when none is left.
    """
    a = ct.array
    air = a < threshold_hu
    lab, n = ndimage.label(air)
    voxel_ml = float(np.prod(ct.spacing)) / 1000.0
    counts = np.bincount(lab.ravel(), minlength=n + 1)
    ids = [i for i in range(1, n + 1) if counts[i] * voxel_ml >= MIN_GAS_ML]
    si_axis, si_high = _superior_face(ct)
    sides = [ax for ax in range(3) if ax != si_axis]
    body = a[::4, ::4, ::4] > threshold_hu
    bk, bj, bi = np.nonzero(body)
    body_x = float(ct.index_to_lps(np.stack([bi, bj, bk], 1) * 4.0)[:, 0].mean()) if len(bk) else 0.0
    objs = ndimage.find_objects(lab)
    rows = []
    for i in ids:
        sl = objs[i - 1]
        vol_ml = counts[i] * voxel_ml
        side = any(sl[ax].start == 0 or sl[ax].stop == a.shape[ax] for ax in sides)
        top_face = sl[si_axis].stop == a.shape[si_axis] if si_high else sl[si_axis].start == 0
        comp = lab[sl] == i
        mean_hu = float(a[sl][comp].mean())
        k, j, ii = np.nonzero(comp)
        step = max(1, len(k) // 50000)  # a lung holds millions of voxels: a sample places it well enough
        pts = ct.index_to_lps(np.stack([ii[::step] + sl[2].start, j[::step] + sl[1].start,
                                        k[::step] + sl[0].start], 1).astype(float))
        lung = mean_hu > -910.0 and (vol_ml > 150.0 or top_face)
        why = ("touches the volume's side" if side else f"{vol_ml:.0f} mL, too large" if vol_ml > MAX_STOMACH_ML
               else "lung-like" if lung or (top_face and vol_ml > 1000.0) else "")
        rows.append({"id": i, "ml": vol_ml, "top_z": float(pts[:, 2].max()), "x": float(pts[:, 0].mean()),
                     "mean_hu": mean_hu, "excluded": why})
    cands = [r for r in rows if not r["excluded"]]
    if not cands:
        raise AnatomyError(f"no stomach gas found: no gas region of at least {MIN_GAS_ML:g} mL inside the body that "
                           "is neither lung nor outside air; place the points (--cardia/--pylorus or "
                           "--points) or pass a segmentation with --mask")
    z_best = max(r["top_z"] for r in cands)
    for r in cands:
        r["score"] = r["ml"] * (1.0 if r["x"] > body_x else 0.35) * float(np.exp(-(z_best - r["top_z"]) / 80.0))
    cands.sort(key=lambda r: -r["score"])
    best = cands[0]
    ratio = cands[1]["score"] / best["score"] if len(cands) > 1 else 0.0
    ev = [f"stomach gas: {best['ml']:.0f} mL, mean {best['mean_hu']:.0f} HU, "
          f"{'left' if best['x'] > body_x else 'right'} of the body's centre; {len(cands) - 1} other gas "
          f"candidate(s) (runner-up score {ratio:.2f} of it), {len(rows) - len(cands)} gas region(s) excluded "
          f"({', '.join(sorted(set(r['excluded'] for r in rows if r['excluded']))) or 'none'})"]
    return lab == best["id"], {"volume_ml": best["ml"], "runner_up_ratio": ratio, "candidates": len(cands),
                               "left": bool(best["x"] > body_x), "evidence": ev}


def points_from_gas(ct: Volume, threshold_hu: float = -500.0, max_snap_mm: float = 20.0) -> AutoPoints:
    """Cardia and pylorus (LPS mm) from the stomach gas of a gas-distended CT (HU), with confidences and evidence."""
    gas, info = find_stomach_gas(ct, threshold_hu)
    # retained water under a flat air-fluid level is lumen too (as the front end adds it): the shape is the whole lumen
    fluid, finfo = fluid_below_level(ct, gas, threshold_hu=threshold_hu)
    lumen = gas | fluid
    lo, hi = bounding_box(lumen, tuple(int(np.ceil(30.0 / s)) for s in ct.spacing))
    ct_c = ct.crop(lo, hi)
    lumen_c = lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    shape = _shape_points(ct_c, lumen_c, gas=True)
    region_conf = (0.5 + 0.5 * float(np.clip(1.5 * (1.0 - info["runner_up_ratio"]), 0.0, 1.0)))
    region_conf *= float(np.clip(info["volume_ml"] / 150.0, 0.0, 1.0))
    if not info["left"]:  # the stomach lies under the left hemidiaphragm: gas on the right is probably bowel
        region_conf *= 0.5
    evidence = info["evidence"] + shape["evidence"]
    if info["volume_ml"] < 150.0:
        evidence.append(f"only {info['volume_ml']:.0f} mL of gas: the stomach is probably not distended; unsure")
    if finfo["fluid_voxels"]:
        evidence.append(f"{finfo['fluid_ml']:.0f} mL of retained fluid under an air-fluid level taken as lumen")
    pts = {}
    for point in ("cardia", "pylorus"):
        s = nearest_true(lumen_c, ct_c, shape[point], max_snap_mm)
        pts[point] = s if s is not None else shape[point]
    return AutoPoints(pts["cardia"], pts["pylorus"], shape["cardia_confidence"] * region_conf,
                      shape["pylorus_confidence"] * region_conf, "gas", {}, None, evidence)


def find_points(ct: Volume, labels: np.ndarray | None = None, names: dict | None = None,
                convention: str | None = None, threshold_hu: float = -500.0, max_snap_mm: float = 20.0) -> AutoPoints:
    """Find the cardia and pylorus (LPS mm) of CT ``ct`` (HU): from ``labels`` (a multi-label segmentation on the
    CT's grid, see :func:`points_from_labels`) when given, else from the stomach gas (:func:`points_from_gas`)."""
    if labels is not None:
        return points_from_labels(ct, labels, names, convention, threshold_hu, max_snap_mm)
    return points_from_gas(ct, threshold_hu, max_snap_mm)


def labels_on_grid(label_volume: Volume, reference: Volume) -> np.ndarray:
    """A label volume's values resampled onto ``reference``'s grid (nearest neighbour, physical space), int32 array."""
    import SimpleITK as sitk

    img = label_volume.to_sitk()
    if img.GetPixelID() not in (sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16, sitk.sitkInt16, sitk.sitkUInt32,
                                sitk.sitkInt32):
        img = sitk.Cast(img, sitk.sitkInt32)
    ref = sitk.Image([int(v) for v in reference.size], sitk.sitkUInt8)
    ref.SetSpacing([float(s) for s in reference.spacing])
    ref.SetOrigin([float(o) for o in reference.origin])
    ref.SetDirection([float(d) for d in reference.direction.ravel()])
    out = sitk.Resample(img, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0, img.GetPixelID())
    return sitk.GetArrayFromImage(out).astype(np.int32)


def auto_points_or_refuse(ct: Volume, labels: np.ndarray | None = None, names: dict | None = None,
                          threshold_hu: float = -500.0, max_snap_mm: float = 20.0) -> AutoPoints:
    """:func:`find_points`, raising PointError (with the best guesses in RAS mm) below ``CONFIDENCE_THRESHOLD``."""
    from .errors import PointError

    found = find_points(ct, labels, names, threshold_hu=threshold_hu, max_snap_mm=max_snap_mm)
    if not found.confident:
        raise PointError(f"the automatic cardia and pylorus are unsure (confidence {found.cardia_confidence:.2f} and "
                         f"{found.pylorus_confidence:.2f}, below {CONFIDENCE_THRESHOLD:g}; from the {found.source}); "
                         f"pass --cardia/--pylorus or --points; best guesses (RAS mm): {found.guesses_ras_text()}")
    return found
