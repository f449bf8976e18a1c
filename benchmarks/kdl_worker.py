"""PyKDL ChainIdSolver_RNE timed on given states; runs under Debian's /usr/bin/python3.

Standard library and PyKDL only (the system interpreter has neither NumPy nor the venv). Reads a
JSON job on stdin: {urdf, joint_names, locked: {name: position}, gravity, Q, V, A, repeats};
writes JSON on stdout: {tau (N×nv, model order), loop_s (one value per repeat), n}.

The KDL chain is built from the URDF XML here (kdl_parser_py is not used): one segment per joint on
the path from the root link to the last actuated joint; bodies hanging off a chain link through
fixed or locked joints (Panda's hand and fingers) are merged into that link's rigid-body inertia.
"""
from __future__ import annotations

import json
import math
import sys
import time
import xml.etree.ElementTree as ET

import PyKDL as kdl


def _floats(text, default):
    return [float(x) for x in text.split()] if text else list(default)


def _rpy(r, p, y):
    """URDF/KDL fixed-axis roll-pitch-yaw: R = Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr]]


def _mm(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def _mv(a, v):
    return [sum(a[i][k] * v[k] for k in range(3)) for i in range(3)]


def _tr(a):
    return [[a[j][i] for j in range(3)] for i in range(3)]


def _axis_angle(axis, angle):
    x, y, z = axis
    c, s, t = math.cos(angle), math.sin(angle), 1 - math.cos(angle)
    return [[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, t * z * z + c]]


def _origin(el):
    o = el.find("origin") if el is not None else None
    xyz = _floats(o.get("xyz") if o is not None else None, (0, 0, 0))
    rpy = _floats(o.get("rpy") if o is not None else None, (0, 0, 0))
    return _rpy(*rpy), xyz


def _compose(t1, t2):
    (r1, p1), (r2, p2) = t1, t2
    return _mm(r1, r2), [a + b for a, b in zip(_mv(r1, p2), p1)]


class Urdf:
    def __init__(self, text, locked):
        root = ET.fromstring(text)
        self.links = {l.get("name"): l for l in root.findall("link")}
        self.joints = {}
        self.children = {}
        for j in root.findall("joint"):
            jtype = j.get("type")
            axis = _floats(j.find("axis").get("xyz") if j.find("axis") is not None else None, (1, 0, 0))
            n = math.sqrt(sum(a * a for a in axis))
            info = dict(name=j.get("name"), type="revolute" if jtype == "continuous" else jtype,
                        parent=j.find("parent").get("link"), child=j.find("child").get("link"),
                        origin=_origin(j), axis=[a / n for a in axis])
            self.joints[info["name"]] = info
            self.children.setdefault(info["parent"], []).append(info)
        self.locked = dict(locked)
        self.parent_joint = {j["child"]: j for j in self.joints.values()}

    def fixed_transform(self, j):
        """parent-link <- child-link transform of a fixed or locked joint."""
        t = j["origin"]
        q = self.locked.get(j["name"], 0.0)
        if j["type"] == "prismatic":
            return _compose(t, ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [a * q for a in j["axis"]]))
        if j["type"] == "revolute":
            return _compose(t, (_axis_angle(j["axis"], q), [0, 0, 0]))
        return t

    def bodies(self, link, transform, exclude):
        """(mass, com, I_about_com) of link and everything fixed to it, in the frame ``transform``."""
        out = []
        inertial = self.links[link].find("inertial")
        if inertial is not None:
            R_i, p_i = _compose(transform, _origin(inertial))
            m = float(inertial.find("mass").get("value"))
            a = {k: float(inertial.find("inertia").get(k, 0.0))
                 for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")}
            I = [[a["ixx"], a["ixy"], a["ixz"]], [a["ixy"], a["iyy"], a["iyz"]],
                 [a["ixz"], a["iyz"], a["izz"]]]
            out.append((m, p_i, _mm(_mm(R_i, I), _tr(R_i))))
        for j in self.children.get(link, []):
            if j["name"] in exclude:
                continue
            if j["type"] != "fixed" and j["name"] not in self.locked:
                raise ValueError(f"{j['name']} branches off the chain: not a serial robot")
            out += self.bodies(j["child"], _compose(transform, self.fixed_transform(j)), exclude)
        return out


def merged_inertia(bodies):
    m = sum(b[0] for b in bodies)
    if m == 0.0:
        return kdl.RigidBodyInertia()
    c = [sum(b[0] * b[1][k] for b in bodies) / m for k in range(3)]
    I = [[0.0] * 3 for _ in range(3)]
    for mb, cb, Ib in bodies:
        d = [cb[k] - c[k] for k in range(3)]
        dd = sum(x * x for x in d)
        for r in range(3):
            for s in range(3):
                I[r][s] += Ib[r][s] + mb * ((dd if r == s else 0.0) - d[r] * d[s])
    return kdl.RigidBodyInertia(m, kdl.Vector(*c), kdl.RotationalInertia(
        I[0][0], I[1][1], I[2][2], I[0][1], I[0][2], I[1][2]))


def _frame(t):
    R, p = t
    return kdl.Frame(kdl.Rotation(*[R[i][j] for i in range(3) for j in range(3)]), kdl.Vector(*p))


def build_chain(urdf, joint_names):
    path = []
    link = urdf.joints[joint_names[-1]]["child"]
    while link in urdf.parent_joint:
        j = urdf.parent_joint[link]
        path.append(j)
        link = j["parent"]
    path.reverse()
    on_path = {j["name"] for j in path}
    chain_joints = [j["name"] for j in path if j["name"] in joint_names]
    if chain_joints != list(joint_names):
        raise ValueError(f"actuated joints {joint_names} are not one serial chain {chain_joints}")
    chain = kdl.Chain()
    identity = ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [0, 0, 0])
    for j in path:
        actuated = j["name"] in joint_names
        F = j["origin"] if actuated else urdf.fixed_transform(j)
        frame = _frame(F)
        if actuated:
            axis = kdl.Vector(*_mv(F[0], j["axis"]))
            kind = kdl.Joint.RotAxis if j["type"] == "revolute" else kdl.Joint.TransAxis
            joint = kdl.Joint(j["name"], frame.p, axis, kind)
        else:
            joint = kdl.Joint(j["name"], kdl.Joint.Fixed)
        inertia = merged_inertia(urdf.bodies(j["child"], identity, on_path))
        chain.addSegment(kdl.Segment(j["child"], joint, frame, inertia))
    return chain


def main():
    job = json.load(sys.stdin)
    chain = build_chain(Urdf(job["urdf"], job.get("locked", {})), job["joint_names"])
    solver = kdl.ChainIdSolver_RNE(chain, kdl.Vector(*job["gravity"]))
    nv = len(job["joint_names"])
    Q, V, A = job["Q"], job["V"], job["A"]
    q, v, a, tau = kdl.JntArray(nv), kdl.JntArray(nv), kdl.JntArray(nv), kdl.JntArray(nv)
    wrenches = [kdl.Wrench() for _ in range(chain.getNrOfSegments())]

    def run(keep):
        out = []
        for qi, vi, ai in zip(Q, V, A):
            for k in range(nv):
                q[k] = qi[k]
                v[k] = vi[k]
                a[k] = ai[k]
            rc = solver.CartToJnt(q, v, a, wrenches, tau)
            if rc < 0:
                raise RuntimeError(f"ChainIdSolver_RNE returned {rc}")
            if keep:
                out.append([tau[k] for k in range(nv)])
        return out

    result = run(True)
    times = []
    for _ in range(int(job.get("repeats", 5))):
        t0 = time.perf_counter()
        run(False)
        times.append(time.perf_counter() - t0)
    json.dump({"tau": result, "loop_s": times, "n": len(Q),
               "kdl_version": getattr(kdl, "__version__", "")}, sys.stdout)


if __name__ == "__main__":
    main()
