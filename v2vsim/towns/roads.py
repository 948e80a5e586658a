"""A town plan's roads as SUMO plain XML (nodes, edges, connections), built into a .net.xml by netconvert.

We draw the nodes and edges ourselves (the plan's arms, curves, side streets and ramps) and let SUMO's own
netconvert do what it does best: lanes, junction outlines, internal lanes, right of way and signal plans.
netconvert comes with the `eclipse-sumo` wheel (`pip install 'v2vsim[towns]'`); running towns needs only libsumo.

Node ids: `C` the main junction at the origin, `A<i>` the end of arm i, `S<i>` the side street's junction on arm
i, `T<i>` the side street's far end. Edge ids: `A<i>_in` / `A<i>_out` towards / away from the main junction (an
arm with a side street is split at `S<i>`: `A<i>_in0` from the fringe to `S<i>`, `A<i>_in` on to `C`, and the same
outwards), `T<i>_in` / `T<i>_out` on the side street.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from v2vsim.towns.plan import ArmPlan, TownPlan

NETCONVERT_MISSING = ("town generation needs SUMO's netconvert on the PATH: pip install 'v2vsim[towns]' "
                      "(the eclipse-sumo wheel)")
_HEADER = re.compile(r"<!-- generated on .*?-->", re.DOTALL)
_SIDE_STREET_M = (70.0, 110.0)  # the side street's length range is fixed by its bearing's draw (see _side_len)


def _unit(deg: float) -> np.ndarray:
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


def _curve(p0: np.ndarray, p1: np.ndarray, shift: float, n: int = 10) -> list[np.ndarray]:
    """A quadratic Bezier from p0 to p1 whose control point is the chord's midpoint moved `shift` to the left."""
    d = p1 - p0
    normal = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9)
    c = (p0 + p1) / 2 + 2 * shift * normal  # the curve passes `shift` from the chord's midpoint
    return [(1 - t) ** 2 * p0 + 2 * (1 - t) * t * c + t ** 2 * p1 for t in np.linspace(0, 1, n)]


def _fmt(points: list[np.ndarray]) -> str:
    return " ".join(f"{p[0]:.2f},{p[1]:.2f}" for p in points)


def _side_len(arm: ArmPlan) -> float:
    lo, hi = _SIDE_STREET_M
    return lo + (hi - lo) * ((abs(arm.side_street_bearing_deg) - 60) / 60)


def _edge(root: ET.Element, eid: str, frm: str, to: str, lanes: int, speed: float, prio: int,
          shape: list[np.ndarray] | None = None) -> None:
    attrs = {"id": eid, "from": frm, "to": to, "numLanes": str(lanes), "speed": f"{speed:.2f}",
             "priority": str(prio)}
    if shape is not None:
        attrs["shape"] = _fmt(shape)
    ET.SubElement(root, "edge", attrs)


def plain_xml(plan: TownPlan) -> tuple[ET.ElementTree, ET.ElementTree, ET.ElementTree]:
    """(nodes, edges, connections) of the plan's roads (module doc for the ids)."""
    nodes, edges, cons = ET.Element("nodes"), ET.Element("edges"), ET.Element("connections")
    ET.SubElement(nodes, "node", {"id": "C", "x": "0.00", "y": "0.00", "type": plan.control})
    centre = np.zeros(2)
    for i, arm in enumerate(plan.arms):
        end = centre + arm.length_m * _unit(arm.bearing_deg)
        ET.SubElement(nodes, "node", {"id": f"A{i}", "x": f"{end[0]:.2f}", "y": f"{end[1]:.2f}", "type": "priority"})
        a = f"A{i}"
        if arm.side_street_at_m is not None:
            s = centre + arm.side_street_at_m * _unit(arm.bearing_deg)
            t = s + _side_len(arm) * _unit(arm.bearing_deg + arm.side_street_bearing_deg)
            ET.SubElement(nodes, "node", {"id": f"S{i}", "x": f"{s[0]:.2f}", "y": f"{s[1]:.2f}", "type": "priority"})
            ET.SubElement(nodes, "node", {"id": f"T{i}", "x": f"{t[0]:.2f}", "y": f"{t[1]:.2f}", "type": "priority"})
            _edge(edges, f"A{i}_in0", a, f"S{i}", arm.lanes_in, arm.speed_mps, arm.priority)
            _edge(edges, f"A{i}_out0", f"S{i}", a, arm.lanes_out, arm.speed_mps, arm.priority)
            _edge(edges, f"A{i}_in", f"S{i}", "C", arm.lanes_in, arm.speed_mps, arm.priority)
            _edge(edges, f"A{i}_out", "C", f"S{i}", arm.lanes_out, arm.speed_mps, arm.priority)
            _edge(edges, f"T{i}_in", f"T{i}", f"S{i}", 1, 8.33, 1)
            _edge(edges, f"T{i}_out", f"S{i}", f"T{i}", 1, 8.33, 1)
            continue
        shape = _curve(end, centre, arm.curve_m) if arm.curve_m else None
        _edge(edges, f"A{i}_in", a, "C", arm.lanes_in, arm.speed_mps, arm.priority, shape)
        if arm.lanes_out > 0:
            _edge(edges, f"A{i}_out", "C", a, arm.lanes_out, arm.speed_mps, arm.priority,
                  shape[::-1] if shape is not None else None)
    if plan.kind == "merge":
        # the ramp (arm 2) joins the outgoing main road (arm 1) on its rightmost lane, and only there: without the
        # explicit connection netconvert would also let it turn back sharply onto arm 0
        ET.SubElement(cons, "connection", {"from": "A2_in", "to": "A1_out", "fromLane": "0", "toLane": "0"})
    return ET.ElementTree(nodes), ET.ElementTree(edges), ET.ElementTree(cons)


def build_net(plan: TownPlan, folder: Path) -> Path:
    """Write the plain XML into `folder` and build `<name>.net.xml` with netconvert; its path."""
    exe = shutil.which("netconvert")
    if exe is None:
        raise RuntimeError(NETCONVERT_MISSING)
    folder.mkdir(parents=True, exist_ok=True)
    nod, edg, con = plain_xml(plan)
    stem = folder / plan.name
    for tree, ext in ((nod, "nod"), (edg, "edg"), (con, "con")):
        ET.indent(tree)
        tree.write(f"{stem}.{ext}.xml", encoding="utf-8", xml_declaration=True)
    net = Path(f"{stem}.net.xml")
    cmd = [exe, "--node-files", f"{stem}.nod.xml", "--edge-files", f"{stem}.edg.xml",
           "--connection-files", f"{stem}.con.xml", "--output-file", str(net),
           "--offset.disable-normalization", "true", "--no-turnarounds", "true",
           "--tls.default-type", "static", "--tls.cycle.time", f"{plan.tls_cycle_s:g}",
           "--no-warnings", "true", "--output.street-names", "false", "--seed", str(plan.seed)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"netconvert failed for {plan.name} ({done.returncode}): {done.stderr.strip()[-400:]}")
    # netconvert's header comment holds the time and the absolute paths: without it a seed gives the same bytes
    text = _HEADER.sub(f"<!-- {plan.name}: built by netconvert from {plan.name}.nod.xml, .edg.xml, .con.xml -->",
                       net.read_text(), count=1)
    net.write_text(text)
    return net
