"""A robot from its URDF: links become bodies, joint limits become #670 and #669, posed by a joint vector.

Read with yourdfpy (the `robot` extra), which parses the file without loading meshes and gives the joint
tree, types, limits, mimic joints, origins and axes; the forward kinematics (FK) that poses the links composes
each joint's origin and motion (trimesh's, as yourdfpy's own FK) from the root (`Robot._fk` says why). Links joined by
fixed joints are one body, whose frame is the link nearest the root; the root body is fixed (it is the
frame every pose is given in). A revolute joint with limits is a #670 limit, a prismatic one a #669,
each with its edge in its two bodies' own coordinates (`local_edge`, contract v1.2): through the joint's
origin along its axis. Continuous joints and joints without `<limit>` carry no limit (their position
still poses the links); mimic, floating and planar joints are listed in `Robot.unmodelled` (and warned
about), never dropped silently: a mimic joint is posed by the FK from the joint it follows.

The joint vector `q` has one position per joint of `Robot.names` (revolute, prismatic, continuous, in the
file's order), or is a mapping from those names (a missing name is at 0, in `reference` and `q_prev` too). Each
joint's reported `coordinate` is its position in `q`, exactly, at any angle: a revolute limit is given its known
coordinate at the previous pose (the wire's `prev_coordinate`), so nothing is wrapped into (-pi, pi].
`x` is measured from the reference configuration (zero by default: then `x` is the position too).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

import numpy as np

from jointlimits.client.errors import InvalidInput
from jointlimits.client.model import Evaluation, Joint, Request
from jointlimits.client.scene import Scene, transforms_to_q
from jointlimits.schemas.constitutions import STRENGTH_DEFAULT

JointVector = Union[Sequence[float], np.ndarray, Mapping[str, float]]
MOVING = ("revolute", "prismatic", "continuous")  # the joints a position in `q` moves


@dataclass(frozen=True)
class RobotJoint:
    """A joint `q` moves: `type` one of `MOVING`; `lower`, `upper` from its `<limit>` (an attribute left out
    is 0, as the URDF spec says), None when it carries no limit (continuous, or no `<limit>`);
    `body_ids` (parent body, child body); `local_edge` (2, 2, 3) `[[l0, l1], [r0, r1]]`: the joint's
    origin and a unit step along its axis, in the parent body's and in the child body's frame."""

    name: str
    type: str
    lower: float | None
    upper: float | None
    body_ids: tuple[int, int]
    local_edge: np.ndarray


@dataclass(frozen=True)
class Reading:
    """One joint at one pose: its `position` (the answer's coordinate, or `q`'s where it has no limit),
    its range, its limit's `energy`, and whether it is `active` (outside its range)."""

    name: str
    type: str
    position: float
    lower: float | None
    upper: float | None
    energy: float
    active: bool


class Robot:
    """A URDF robot for the service: `request(q)` poses it and builds the request, `readings` reads the answer.

    >>> from jointlimits import LocalClient, Robot
    >>> robot = Robot.load("tests/robots/arm7.urdf")  # from the repository's root; it warns of its mimic joint
    >>> q = {"joint1": -3.81, "joint4": -1.0, "finger_left": 0.02}  # by name, or a list in `robot.names`' order
    >>> result = LocalClient().evaluate(robot.request(q))  # a joint left out is at 0
    >>> [r.name for r in robot.readings(result, q) if r.active]  # past their limits: energy, gradient, Hessian
    ['joint1']
    """

    def __init__(self, urdf: Any) -> None:
        """From a loaded `yourdfpy.URDF` (its `robot`: a scene graph is not needed); `Robot.load` reads a file."""
        self.urdf = urdf
        self.unmodelled: list[str] = []
        names = [jt.name for jt in urdf.robot.joints]  # yourdfpy reads repeated names; `q` by name cannot tell them
        if twice := sorted({n for n in names if names.count(n) > 1}):
            raise ValueError(f"{urdf.robot.name}: joint names must be unique: {twice} is more than one joint's")
        moved = {jt.child for jt in urdf.robot.joints}  # the root by yourdfpy's rule (no `base_link` without a graph)
        root = next((link.name for link in urdf.robot.links if link.name not in moved), None)
        if root is None:  # yourdfpy reads a file whose joints close a loop, with no link at the root
            raise ValueError(f"{urdf.robot.name}: no root link (" + ("each link is some joint's child: a loop)"
                                                                      if urdf.robot.links else "no <link> at all)"))
        self._joint = {jt.name: jt for jt in urdf.robot.joints}
        for jt in urdf.robot.joints:  # a mimic of a mimic follows that one's position (URDF): no loop, no unknown name
            chain = [jt.name]
            while (m := self._joint[chain[-1]].mimic) is not None:
                if m.joint not in self._joint or m.joint in chain:
                    raise ValueError(f"{urdf.robot.name}: joint {chain[-1]} mimics {m.joint}, " + (
                        "no joint of the file" if m.joint not in self._joint else f"a loop of mimics {chain}"))
                chain.append(m.joint)
        kids: dict[str, list[Any]] = {}
        self._axis: dict[str, np.ndarray] = {}  # each moving joint's unit axis (the caller's `urdf` is left as it is)
        for jt in urdf.robot.joints:
            kids.setdefault(jt.parent, []).append(jt)
            if jt.origin is not None and not np.isfinite(jt.origin).all():  # else named later at a limit below it
                raise ValueError(f"joint {jt.name}: its <origin> is not finite (xyz and rpy are finite numbers)")
            if jt.type not in (*MOVING, "fixed", "floating", "planar"):  # yourdfpy reads any: it moved as fixed
                raise ValueError(f"joint {jt.name}: its type {jt.type!r} is none of URDF's (revolute, continuous, "
                                 "prismatic, fixed, floating, planar)")
            if jt.type in MOVING:  # yourdfpy would slide a prismatic joint by q * axis as written: make it unit
                length = float(np.linalg.norm(jt.axis))
                if not 0 < length < math.inf:
                    raise ValueError(f"joint {jt.name}: its axis {jt.axis.tolist()} has no direction")
                self._axis[jt.name] = jt.axis / length
        frame, order, todo = {root: root}, [root], [root]  # frame: a link's body frame; order: the bodies' frames
        self._chain: list[Any] = []  # the joints joined to the root, each after the one that moves its parent
        while todo:
            for jt in kids.get(todo.pop(0), []):
                self._chain.append(jt)
                frame[jt.child] = frame[jt.parent] if jt.type == "fixed" else jt.child
                order += [] if jt.type == "fixed" else [jt.child]
                todo.append(jt.child)
        for link in urdf.robot.links:
            if link.name not in frame:  # part of the root's body (yourdfpy's FK has no path to it)
                frame[link.name] = root
                self.unmodelled.append(f"link {link.name}: not joined to {root}, fixed to it")
        self.links = frame
        self.frames = order
        self.names = [jt.name for jt in urdf.robot.joints if jt.type in MOVING and jt.mimic is None]
        zero = self._fk({})
        self.joints: list[RobotJoint] = []
        for jt in urdf.robot.joints:
            if jt.mimic is not None:
                m = jt.mimic
                self.unmodelled.append(f"{jt.type} joint {jt.name}: mimics {m.joint} "
                                       f"({m.multiplier:g} x {m.joint} + {m.offset:g}), posed by FK, no limit")
            elif jt.type in ("floating", "planar"):
                self.unmodelled.append(f"{jt.type} joint {jt.name}: not modelled, its child stays at the joint's origin")
            elif jt.type in MOVING:
                if jt.child not in order:  # in another tree: yourdfpy's FK has no path to it
                    raise ValueError(f"{urdf.robot.name}: joint {jt.name} moves link {jt.child}, not joined to {root}")
                i, j = order.index(frame[jt.parent]), order.index(jt.child)
                M = np.linalg.solve(zero[i], zero[j])  # the joint's frame at zero in the parent body's
                a = self._axis[jt.name]
                edge = [[M[:3, 3], M[:3, 3] + M[:3, :3] @ a], [np.zeros(3), a]]
                limited = jt.type != "continuous" and jt.limit is not None
                lo, up = ((jt.limit.lower or 0.0, jt.limit.upper or 0.0) if limited else (None, None))  # URDF: 0
                self.joints.append(RobotJoint(jt.name, jt.type, lo, up, (i, j), np.array(edge, dtype=np.float64)))
        if self.unmodelled:
            warnings.warn(f"{urdf.robot.name}: not modelled by the joint limits: " + "; ".join(self.unmodelled),
                          stacklevel=3)  # the caller of `Robot.load`
        self._ref = (np.zeros(len(self.names)).tobytes(), transforms_to_q(zero))  # the default reference's poses
        _, self.handles = self.scene(np.zeros(len(self.names)))  # checks every limit once, by name

    @classmethod
    def load(cls, path: str | Path) -> Robot:
        """Read a URDF file (meshes are not loaded: a robot whose mesh files are absent reads the same)."""
        try:
            import yourdfpy
        except ImportError as e:  # pragma: no cover (the `robot` extra)
            raise ImportError("reading a URDF needs yourdfpy: pip install yourdfpy (the robot extra)") from e
        from lxml import etree  # yourdfpy's parser, strict: yourdfpy logs its error and reads what it can recover

        data = Path(path).read_bytes()  # a missing file: the OSError
        try:  # what is wrong said first, not yourdfpy's KeyError or "Invalid input"
            root = etree.fromstring(data, strict := etree.XMLParser())
        except etree.XMLSyntaxError as e:  # a prefix never declared (<xacro:...>, <sensor:...>): yourdfpy drops them
            if any(x.domain_name != "NAMESPACE" for x in strict.error_log):
                raise ValueError(f"{path}: not XML ({e.msg})") from None
            root = etree.fromstring(data, etree.XMLParser(recover=True))
        if root.tag != "robot" or "name" not in root.attrib:
            raise ValueError(f"{path}: not a URDF: its root element is <{root.tag}>, a URDF's is <robot name=...>"
                             if root.tag != "robot" else f"{path}: its <robot> has no name (URDF requires one)")
        links = {link.get("name") for link in root.findall("link")}  # else yourdfpy's "x not in list", AttributeError
        if odd := [(j.get("name"), end, at) for j in root.findall("joint") for end in ("parent", "child")
                   if (at := j.xpath(f"string({end}/@link)")) not in links]:
            name, end, at = odd[0]
            raise ValueError(f"{path}: joint {name}: its <{end} link={at!r}> names no <link> of the file")
        try:
            urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
        except Exception as e:  # yourdfpy's own exceptions (ValueError, KeyError, lxml's), said with the file's name
            raise ValueError(f"{path}: not a URDF yourdfpy reads ({type(e).__name__}: {e})") from e
        return cls(urdf)

    def vector(self, q: JointVector | None, name: str = "q") -> np.ndarray:
        """`q` as positions (n,) in `names` order (None: zeros); `ValueError` naming what is wrong."""
        if q is None:
            return np.zeros(len(self.names))
        if isinstance(q, Mapping):
            unknown = sorted(set(q) - set(self.names))
            if unknown:
                raise ValueError(f"{name}: no moving joint named {unknown} (the joints are {self.names})")
            q = [q.get(n, 0.0) for n in self.names]
        given = np.asarray(q, dtype=object)  # NumPy reads "1", True, None, and a complex number's real part alone
        for n, x in zip(self.names, given if given.shape == (len(self.names),) else []):
            if x is None or isinstance(x, (bool, np.bool_, str, bytes, complex, np.complexfloating)):  # as `Scene`
                kind = ("None" if x is None else "a boolean" if isinstance(x, (bool, np.bool_)) else
                        "a string" if isinstance(x, (str, bytes)) else "a complex number")
                raise ValueError(f"{name}: a position is a number, not {kind} ({n}: {x!r})")
        try:  # a position that is no number: NumPy's words, after the vector's name
            v = np.asarray(q, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name}: {e}") from None
        if v.shape != (len(self.names),):
            raise ValueError(f"{name}: {len(self.names)} positions, one per joint of {self.names}, got shape {v.shape}")
        if not np.isfinite(v).all():
            raise ValueError(f"{name}: not finite at {[self.names[k] for k in np.flatnonzero(~np.isfinite(v))]}")
        return v

    def _fk(self, q: Mapping[str, float]) -> list[np.ndarray]:
        """Each body's frame (4, 4) in the root's at the positions `q`: each joint's origin and motion as yourdfpy
        reads and moves them (a mimic joint follows its joint), composed from the root. Not yourdfpy's own FK: its
        scene graph (trimesh) drops a transform within 1e-8 of the identity from a link's path and keeps a joint's
        old one when the new one is within 1e-8 of it, so a joint 1e-9 rad or m from zero read 0."""
        import trimesh.transformations as tra  # yourdfpy's (it depends on trimesh): the same joint motions

        def position(jt: Any) -> float:  # a mimic joint: multiplier x its joint's position + offset (0 if not moving)
            m = jt.mimic
            return float(q.get(jt.name, 0.0)) if m is None else position(self._joint[m.joint]) * m.multiplier + m.offset

        at = {self.frames[0]: np.eye(4)}  # the root
        for jt in self._chain:
            v, a = position(jt), self._axis.get(jt.name)
            move = (tra.translation_matrix(v * a) if jt.type == "prismatic" else
                    tra.rotation_matrix(v, a) if jt.type in ("revolute", "continuous") else None)  # fixed, ...
            origin = np.eye(4) if jt.origin is None else jt.origin
            at[jt.child] = at[jt.parent] @ (origin if move is None else origin @ move)
        return [at[link] for link in self.frames]

    def poses(self, q: JointVector | None) -> np.ndarray:
        """Every body's 12 DOFs (B, 12) at the joint vector `q`: what a session's `evaluate` and `commit` take."""
        return transforms_to_q(self._fk(dict(zip(self.names, self.vector(q)))))

    def _poses_at(self, v: np.ndarray, *known: tuple[bytes, np.ndarray]) -> tuple[bytes, np.ndarray]:
        """(`v`'s bytes, its poses (B, 12)): a `known` pair's if its bytes match (-0.0 is not 0.0), else FK's."""
        return next((k for k in known if k[0] == v.tobytes()), None) or (v.tobytes(), self.poses(v))

    def scene(self, q: JointVector, q_prev: JointVector | None = None, reference: JointVector | None = None,
              strength: float | Mapping[str, float] = STRENGTH_DEFAULT) -> tuple[Scene, dict[str, Joint]]:
        """The robot as a `Scene`, and each limited joint's handle by name. Bodies are posed by FK at `q`,
        at `q_prev` (default `q`) and at `reference` (the pose the joints were built at, default zero, the
        request's `q_ref`). Each limit's `offset` is its joint's reference position and a revolute limit's
        `prev_coordinate` its position in `q_prev`: so the coordinate is the position in `q` (exact past
        +-pi and over turns; a revolute limit pi or more from `q_prev` is a ValueError) and `x` = position -
        reference. `strength`: one number, or one per limited joint by name (others keep the default)."""
        v = self.vector(q)
        v_prev = v if q_prev is None else self.vector(q_prev, "q_prev")
        v_ref = self.vector(reference, "reference")
        if isinstance(strength, Mapping) and (unknown := sorted(set(strength) - set(self.handles))):
            raise ValueError(f"strength: no limited joint named {unknown} (the limited joints: {list(self.handles)})")
        at_q = self._poses_at(v)  # one FK at q; q_prev equal to q and the last reference reuse theirs
        at_ref = self._ref = self._poses_at(v_ref, self._ref)  # kept for the next call; this one reads its own
        scene = Scene()
        for now, prev, ref in zip(at_q[1], self._poses_at(v_prev, at_q)[1], at_ref[1]):
            scene.add_body(now, prev=prev, ref=ref)
        handles: dict[str, Joint] = {}
        for kind in ("revolute", "prismatic"):  # one batch each, in this order: the handles never change
            for jt in (jt for jt in self.joints if jt.type == kind and jt.lower is not None):
                k = self.names.index(jt.name)
                s = strength.get(jt.name, STRENGTH_DEFAULT) if isinstance(strength, Mapping) else strength
                add = scene.add_revolute_limit if kind == "revolute" else scene.add_prismatic_limit
                state = {"prev_coordinate": v_prev[k]} if kind == "revolute" else {}  # 669's slide needs no state
                if kind == "revolute" and not abs(v[k] - v_prev[k]) < math.pi:  # the turn between them is wrapped
                    raise ValueError(f"joint {jt.name}: q is {abs(v[k] - v_prev[k]):.6g} rad from q_prev; the "
                                     "coordinate is exact only for a step of less than pi")
                try:
                    handles[jt.name] = add(*jt.body_ids, lower=jt.lower, upper=jt.upper, strength=s,
                                           offset=v_ref[k], local_edge=jt.local_edge, **state)
                except InvalidInput as e:  # name the joint, as the file does
                    raise ValueError(f"joint {jt.name}: {e}") from e
        return scene, handles

    def request(self, q: JointVector, q_prev: JointVector | None = None, reference: JointVector | None = None,
                strength: float | Mapping[str, float] = STRENGTH_DEFAULT, **options: Any) -> Request:
        """`scene(...)`'s request; `options` as `Scene.request`'s (outputs, hessian_mode, active_only, layout)."""
        return self.scene(q, q_prev, reference, strength)[0].request(**options)

    def readings(self, result: Evaluation, q: JointVector) -> list[Reading]:
        """Per moving joint, in `names` order: its position, range, energy and whether it is active."""
        v = self.vector(q)
        out = []
        for jt in self.joints:
            k = self.names.index(jt.name)
            if jt.name not in self.handles:
                out.append(Reading(jt.name, jt.type, float(v[k]), None, None, 0.0, False))
                continue
            r = result.joint(self.handles[jt.name])
            position = float(v[k]) if r.coordinate is None else r.coordinate  # None: inside, under active_only
            out.append(Reading(jt.name, jt.type, position, jt.lower, jt.upper, r.energy,
                               not jt.lower <= position <= jt.upper))  # type: ignore[operator]
        return out


def plot(readings: Sequence[Reading], path: str | Path | None = None, title: str = "") -> Any:
    """Each joint's position inside its range (drawn from `lower` to `upper`), outside ones (active, penalised)
    in red, with its numbers beside; a joint without a limit is listed. Saved to `path` when given; returns
    the matplotlib `Figure` (no pyplot: no window, no backend chosen). Needs matplotlib (the `plot` extra)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover (the `plot` extra)
        raise ImportError("the picture needs matplotlib: pip install matplotlib (the plot extra)") from e
    fig = Figure(figsize=(10, 0.45 * len(readings) + 1.2))
    ax = fig.subplots()
    beside = ax.get_yaxis_transform()  # x in the axes' fraction, y in rows: the numbers' column right of the plot
    spans = [0.0, 1.0]
    for row, r in enumerate(reversed(readings)):
        unit = "rad" if r.type != "prismatic" else "m"
        if r.lower is None:
            ax.text(1.03, row, f"{r.position:.4g} {unit}, no limit", transform=beside, va="center", color="0.4")
            continue
        width = r.upper - r.lower  # type: ignore[operator]
        at = 0.5 if width == 0 else (r.position - r.lower) / width  # the range is [0, 1] on every row
        spans.append(at)
        color = "tab:red" if r.active else "tab:blue"
        ax.barh(row, 1.0, height=0.5, color="0.9", edgecolor="0.6")
        ax.plot([at], [row], marker="D", color=color, markersize=7)
        ax.text(1.03, row, f"{r.position:.4g} in [{r.lower:.4g}, {r.upper:.4g}] {unit}"
                + (f", E = {r.energy:.3g}" if r.active else ""), transform=beside, va="center", color=color)
    ax.set_yticks(range(len(readings)), [r.name for r in reversed(readings)])
    ax.set_ylim(-0.6, len(readings) - 0.4)
    ax.set_xlim(min(spans) - 0.1, max(spans) + 0.1)
    ax.set_xticks([0, 1], ["lower", "upper"])
    ax.set_title(title or "joint positions in their ranges (red: outside, penalised)")
    fig.subplots_adjust(left=0.12, right=0.6, top=0.9, bottom=0.12)
    if path is not None:
        fig.savefig(path, dpi=100)
    return fig
