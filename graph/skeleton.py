"""Skeletons as data: a kinematic tree read from a TOML spec, or free points for any animal.

A *kinematic* skeleton has P pose parameters ``q``. Segment k has a rotation built from its listed
axes, applied after its parent's (passive rotations)::

    RI_k = R_a1(q_i1) R_a2(q_i2) ... RI_parent(k)        (RI_world = I)
    rot_x(a) = [[1,0,0],[0,c,s],[0,-s,c]]
    rot_y(a) = [[c,0,-s],[0,1,0],[s,0,c]]
    rot_z(a) = [[c,s,0],[-s,c,0],[0,0,1]]

A point is either a root, whose position is three parameters, or
``p = p_base + RI_segment^T offset``. Markers are the named points DeepLabCut tracks.

Body proportions: every point with an offset belongs to a *length group* whose one scale factor
``s_g`` multiplies its offset (``offset_k = s_g u_k``, the spec's offset ``u_k`` giving the
direction and the model's length). A point's group is its ``length_group`` in the spec, by default
its name without an ``l_``/``r_`` side prefix, so that left and right share one length.
:meth:`Skeleton.scaled` is the skeleton of another animal's proportions.

The *points* skeleton makes every marker a root point of its own: the same motion model and robust
loss, no kinematics; optional soft bone-length terms tie pairs of markers.

The tree is flattened to integer arrays (:class:`Skeleton.arrays`) that the compiled kernels in
:mod:`graph.solve.kernels` walk.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from graph.errors import NESTED_TOO_DEEPLY, InputError

AXES = {"x": 0, "y": 1, "z": 2}
# a side in a bodypart's name: a word of its own (l_eye, front_left_paw, Ear_R, Shoulder_left) or a capital
# prefix before a capital or digit (OpenPose's LShoulder, a fly's L1A)
SIDE_WORDS = {"l": "left", "left": "left", "r": "right", "right": "right"}
SIDE_PREFIX = re.compile(r"^(L|R|Left|Right)(?=[A-Z0-9])(.+)$")
POINTS_PROCESS_NOISE = 60.0  # std of the per-frame change of a free point's acceleration (m/s^2)
# the nine arrays of :meth:`SkeletonArrays.kernel_args`, seg_parent .. marker_dep
KernelArgs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                   np.ndarray]


@dataclass
class SkeletonArrays:
    """The tree as arrays for the kernels (S segments, K points, M markers, P parameters)."""

    seg_parent: np.ndarray  # (S,) parent segment index, -1 for the world
    seg_axis: np.ndarray  # (S, 3) axis code 0/1/2 in product order, -1 unused
    seg_param: np.ndarray  # (S, 3) parameter index of each axis
    pt_base: np.ndarray  # (K,) base point index, -1 for a root
    pt_seg: np.ndarray  # (K,) segment whose rotation carries the offset
    pt_root: np.ndarray  # (K, 3) parameter indices of a root point's x, y, z
    pt_offset: np.ndarray  # (K, 3)
    marker_point: np.ndarray  # (M,) point index of each marker
    marker_dep: np.ndarray = field(init=False)  # (M, D) parameters each marker depends on, padded with -1

    def __post_init__(self) -> None:
        self.marker_dep = _marker_dependencies(self)

    def kernel_args(self) -> KernelArgs:
        """The arrays in the order the kernels in :mod:`graph.solve.kernels` take them."""
        return (self.seg_parent, self.seg_axis, self.seg_param, self.pt_base, self.pt_seg, self.pt_root,
                self.pt_offset, self.marker_point, self.marker_dep)


def _marker_dependencies(a: "SkeletonArrays") -> np.ndarray:
    """Which parameters move each marker: its root's, and every rotation on its chain."""
    seg_dep: list[set[int]] = []
    for k in range(len(a.seg_parent)):
        own = {int(p) for p, ax in zip(a.seg_param[k], a.seg_axis[k]) if ax >= 0}
        seg_dep.append(own | (seg_dep[a.seg_parent[k]] if a.seg_parent[k] >= 0 else set()))
    pt_dep: list[set[int]] = []
    for k in range(len(a.pt_base)):
        if a.pt_base[k] < 0:
            pt_dep.append({int(p) for p in a.pt_root[k]})
        else:
            pt_dep.append(pt_dep[a.pt_base[k]] | seg_dep[a.pt_seg[k]])
    deps = [sorted(pt_dep[p]) for p in a.marker_point]
    D = max((len(d) for d in deps), default=0)
    out = np.full((len(deps), max(D, 1)), -1, dtype=np.int64)
    for m, d in enumerate(deps):
        out[m, : len(d)] = d
    return out


@dataclass
class Skeleton:
    name: str
    kind: str  # "kinematic" or "points"
    param_names: list[str]
    process_noise: np.ndarray  # (P,)
    lower: np.ndarray  # (P,) -inf where unbounded
    upper: np.ndarray  # (P,)
    markers: list[str]
    arrays: SkeletonArrays
    bones: list[tuple[str, str]] = field(default_factory=list)
    segments: list[str] = field(default_factory=list)
    description: str = ""
    measurement_std_px: float = 5.0
    length_groups: list[str] = field(default_factory=list)  # G body-proportion groups
    point_group: np.ndarray | None = None  # (K,) each point's length group, -1 for none (a root)

    @property
    def model_lengths(self) -> np.ndarray:
        """The model's length (m) of each length group (G,): its first point's offset length."""
        K = len(self.arrays.pt_base)
        out = np.zeros(len(self.length_groups))
        for k in range(K - 1, -1, -1):
            if self.point_group is not None and self.point_group[k] >= 0:
                out[self.point_group[k]] = float(np.linalg.norm(self.arrays.pt_offset[k]))
        return out

    def scales_for(self, lengths: dict[str, float]) -> np.ndarray:
        """Each length group's scale (G,) for ``lengths`` (m per group name; a group not named keeps 1)."""
        model = self.model_lengths
        return np.array([float(lengths[g]) / model[i] if g in lengths else 1.0
                         for i, g in enumerate(self.length_groups)])

    def scaled(self, scales: np.ndarray) -> "Skeleton":
        """The skeleton with each length group's offsets multiplied by ``scales`` (G,)."""
        scales = np.asarray(scales, dtype=float)
        if scales.shape != (len(self.length_groups),):
            raise ValueError(f"{len(self.length_groups)} length scales needed, not {scales.shape}")
        group = self.point_group if self.point_group is not None else np.full(len(self.arrays.pt_base), -1)
        factor = np.where(group >= 0, scales[np.maximum(group, 0)], 1.0)
        arrays = replace(self.arrays, pt_offset=self.arrays.pt_offset * factor[:, None])
        return replace(self, arrays=arrays)

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def angle_params(self) -> np.ndarray:
        """Parameter indices of the rotation angles (a pose is the same with any of them 2 pi apart)."""
        a = self.arrays
        return np.unique(a.seg_param[(a.seg_axis >= 0) & (a.seg_param >= 0)]).astype(np.int64)

    @property
    def root_params(self) -> np.ndarray:
        """Parameter indices of the first root point (the head for the cheetah)."""
        return self.arrays.pt_root[0]

    @property
    def bone_index(self) -> np.ndarray:
        """Bones as (B, 2) marker indices."""
        idx = {m: i for i, m in enumerate(self.markers)}
        return np.array([(idx[a], idx[b]) for a, b in self.bones], dtype=np.int64).reshape(-1, 2)

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    def positions(self, q: np.ndarray) -> np.ndarray:
        """Marker positions (..., M, 3) for pose parameters (..., P), by forward kinematics."""
        from graph.kinematics import fk_batch

        q = np.asarray(q, dtype=np.float64)
        flat = q.reshape(-1, q.shape[-1])
        pos = fk_batch(flat, *self.arrays.kernel_args())
        return pos.reshape(q.shape[:-1] + (len(self.markers), 3))

    def positions_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Marker positions (M, 3) and ``d p / d q`` (M, 3, P) for one pose."""
        from graph.kinematics import fk_jacobian

        return fk_jacobian(np.asarray(q, dtype=np.float64), *self.arrays.kernel_args())


_ANGLE = re.compile(r"^\s*(-?)\s*(?:(\d*\.?\d*)\s*\*?\s*)?pi\s*(?:/\s*(\d*\.?\d+))?\s*$")


def _parse_bound(value, where: str) -> float:
    """A bound as a number or a string such as ``"-pi/6"``, ``"pi/1.5"``, ``"2*pi"``, ``"inf"``."""
    if isinstance(value, (int, float)):
        return float(value)
    s = str(value).strip().lower()
    try:
        return float(s)
    except ValueError:
        pass
    m = _ANGLE.match(s)
    if not m:
        raise InputError(f"bad bound {value!r} in {where}")
    sign = -1.0 if m.group(1) else 1.0
    factor = float(m.group(2)) if m.group(2) else 1.0
    div = float(m.group(3)) if m.group(3) else 1.0
    return sign * factor * math.pi / div


def available_skeletons() -> list[str]:
    """Names accepted by :func:`load_skeleton`: the shipped specs and ``points``."""
    names = sorted(p.name[:-5] for p in resources.files("graph.skeletons").iterdir() if p.name.endswith(".toml"))
    return names + ["points"]


def load_skeleton(spec: str | Path, bodyparts: list[str] | None = None,
                  bone_pairs: list[tuple[str, str]] | None = None) -> Skeleton:
    """A skeleton by name (``cheetah``, ``points``) or from a TOML file.

    ``points`` needs the bodyparts: one free point per bodypart, in that order.
    """
    spec_s = str(spec)
    if spec_s == "points":
        if not bodyparts:
            raise InputError("the points skeleton needs the keypoint files' bodyparts")
        return points_skeleton(bodyparts, bone_pairs)
    path = Path(spec_s)
    if path.suffix != ".toml" and not path.exists():
        res = resources.files("graph.skeletons") / f"{spec_s}.toml"
        if not res.is_file():
            raise InputError(f"unknown skeleton {spec_s!r}: use one of {', '.join(available_skeletons())} "
                             "or a path to a skeleton .toml file")
        text, where = res.read_text(), f"{spec_s}.toml"
    else:
        if not path.is_file():
            raise InputError("skeleton file not found", path)
        text, where = path.read_text(errors="replace"), path.name
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise InputError(f"{where}: {NESTED_TOO_DEEPLY}") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{where}: not a valid TOML skeleton spec ({e})") from None
    try:
        return _from_spec(data, where)
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, InputError):
            raise
        raise InputError(f"{where}: bad skeleton spec ({type(e).__name__}: {e})") from None


def _from_spec(data: dict, where: str) -> Skeleton:
    params = data["params"]
    names = [p["name"] for p in params]
    if len(set(names)) != len(names):
        raise InputError(f"{where}: duplicate parameter names")
    pidx = {n: i for i, n in enumerate(names)}
    noise = np.array([float(p.get("noise", 1.0)) for p in params])
    lower = np.full(len(params), -np.inf)
    upper = np.full(len(params), np.inf)
    for i, p in enumerate(params):
        if "bounds" in p:
            lo, hi = p["bounds"]
            lower[i], upper[i] = _parse_bound(lo, where), _parse_bound(hi, where)
            if not lower[i] < upper[i]:
                raise InputError(f"{where}: bounds of {p['name']} are empty")

    segs = data.get("segments", [])
    sidx: dict[str, int] = {}
    seg_parent = np.full(len(segs), -1, dtype=np.int64)
    seg_axis = np.full((len(segs), 3), -1, dtype=np.int64)
    seg_param = np.full((len(segs), 3), -1, dtype=np.int64)
    for k, s in enumerate(segs):
        parent = s.get("parent", "world")
        if parent != "world":
            if parent not in sidx:
                raise InputError(f"{where}: segment {s['name']} comes before its parent {parent}")
            seg_parent[k] = sidx[parent]
        rot = s.get("rotation", [])
        if len(rot) > 3:
            raise InputError(f"{where}: segment {s['name']} has more than three rotation axes")
        for j, (axis, pname) in enumerate(rot):
            if axis not in AXES or pname not in pidx:
                raise InputError(f"{where}: segment {s['name']}: bad rotation axis {axis!r} or parameter {pname!r}")
            seg_axis[k, j] = AXES[axis]
            seg_param[k, j] = pidx[pname]
        sidx[s["name"]] = k

    pts = data["points"]
    kidx: dict[str, int] = {}
    pt_base = np.full(len(pts), -1, dtype=np.int64)
    pt_seg = np.full(len(pts), -1, dtype=np.int64)
    pt_root = np.full((len(pts), 3), -1, dtype=np.int64)
    pt_offset = np.zeros((len(pts), 3))
    markers, marker_point = [], []
    groups: list[str] = []
    pt_group = np.full(len(pts), -1, dtype=np.int64)
    for k, p in enumerate(pts):
        if "root" in p:
            pt_root[k] = [pidx[n] for n in p["root"]]
        else:
            if p["base"] not in kidx:
                raise InputError(f"{where}: point {p['name']} comes before its base {p['base']}")
            if p["segment"] not in sidx:
                raise InputError(f"{where}: point {p['name']}: unknown segment {p['segment']}")
            pt_base[k] = kidx[p["base"]]
            pt_seg[k] = sidx[p["segment"]]
            pt_offset[k] = np.asarray(p["offset"], dtype=float)
            if np.linalg.norm(pt_offset[k]) > 0:
                group = str(p.get("length_group", _side_free(p["name"])))
                if group not in groups:
                    groups.append(group)
                pt_group[k] = groups.index(group)
        kidx[p["name"]] = k
        if p.get("marker", True):
            markers.append(p["name"])
            marker_point.append(k)
    bones = [tuple(b) for b in data.get("bones", [])]
    for a, b in bones:
        if a not in markers or b not in markers:
            raise InputError(f"{where}: bone {a}-{b} names an unknown marker")
    arrays = SkeletonArrays(seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                            np.array(marker_point, dtype=np.int64))
    return Skeleton(name=data.get("name", where.removesuffix(".toml")), kind="kinematic", param_names=names,
                    process_noise=noise, lower=lower, upper=upper, markers=markers, arrays=arrays,
                    bones=bones, segments=list(sidx), description=data.get("description", ""),
                    measurement_std_px=float(data.get("measurement_std_px", 5.0)), length_groups=groups,
                    point_group=pt_group)


def side_of(name: str) -> tuple[str, str] | None:
    """``("left" | "right", the name without its side)`` for a bodypart named by a side, else None:
    ``l_eye`` -> ``("left", "eye")``, ``front_right_paw`` -> ``("right", "front_paw")``, ``Ear_R`` ->
    ``("right", "Ear")``, ``LShoulder`` -> ``("left", "Shoulder")``, ``R1A`` -> ``("right", "1A")``. A side is
    a word between separators (``_ - . `` or a space; one such word only) or a capital prefix before a capital
    or a digit (:data:`SIDE_WORDS`, :data:`SIDE_PREFIX`)."""
    parts = re.split(r"([_\-.\s]+)", name)  # words at even places, separators between
    sided = [k for k in range(0, len(parts), 2) if parts[k].lower() in SIDE_WORDS]
    if len(sided) == 1 and len(parts) > 1:
        k = sided[0]
        rest = parts[:k] + parts[k + 2:] if k + 1 < len(parts) else parts[:k - 1]
        return SIDE_WORDS[parts[k].lower()], "".join(rest)
    m = SIDE_PREFIX.match(name)
    if m:
        return SIDE_WORDS[m.group(1).lower()[0]], m.group(2)
    return None


def left_right_pairs(markers: list[str]) -> list[tuple[int, int]]:
    """Index pairs ``(left, right)`` of ``markers`` whose names differ only by their side
    (:func:`side_of`): the limbs a 2D tracker may swap."""
    found: dict[str, dict[str, int]] = {}
    for i, m in enumerate(markers):
        side = side_of(m)
        if side is not None:
            found.setdefault(side[1], {})[side[0]] = i
    return [(at["left"], at["right"]) for at in found.values() if len(at) == 2]


def _side_free(name: str) -> str:
    """A point's default length group: its name without its side (``l_eye`` -> ``eye``, :func:`side_of`)."""
    side = side_of(name)
    return side[1] if side is not None else name


def points_skeleton(bodyparts: list[str], bone_pairs: list[tuple[str, str]] | None = None,
                    noise: float = POINTS_PROCESS_NOISE) -> Skeleton:
    """Every bodypart a free 3D point: parameters ``<m>_x, <m>_y, <m>_z``."""
    M = len(bodyparts)
    names = [f"{m}_{c}" for m in bodyparts for c in "xyz"]
    bones = [(a, b) for a, b in (bone_pairs or [])]
    for a, b in bones:
        if a not in bodyparts or b not in bodyparts:
            raise InputError(f"bone {a}-{b} names a bodypart that is not in the keypoint files")
    arrays = SkeletonArrays(
        seg_parent=np.zeros(0, dtype=np.int64), seg_axis=np.zeros((0, 3), dtype=np.int64),
        seg_param=np.zeros((0, 3), dtype=np.int64), pt_base=np.full(M, -1, dtype=np.int64),
        pt_seg=np.full(M, -1, dtype=np.int64), pt_root=np.arange(3 * M, dtype=np.int64).reshape(M, 3),
        pt_offset=np.zeros((M, 3)), marker_point=np.arange(M, dtype=np.int64))
    return Skeleton(name="points", kind="points", param_names=names, process_noise=np.full(3 * M, noise),
                    lower=np.full(3 * M, -np.inf), upper=np.full(3 * M, np.inf), markers=list(bodyparts),
                    arrays=arrays, bones=bones, description="free 3D points, one per bodypart",
                    point_group=np.full(M, -1, dtype=np.int64))
