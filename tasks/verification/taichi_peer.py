"""A Taichi MLS-MPM peer solver for benchmarking (written from Hu et al. 2018, "A Moving Least Squares Material
Point Method with Displacement Discontinuity and Two-Way Rigid Body Coupling").

3D, quadratic B-splines, APIC/MLS transfers, fixed-corotated elasticity, gravity, slip walls on a ``bound``-node
boundary layer (the floor is the bottom wall).  One substep = clear grid -> P2G -> grid update -> G2P, each a
Taichi parallel loop, the usual structure of Taichi MPM codes.  The rotation of the fixed-corotated stress comes
from ``polar="svd"`` (Taichi's 3x3 ``ti.svd``, R = U V^T - what Taichi MPM codes use) or ``polar="quat"`` (the
same warm-started quaternion iteration as the Warp solver, ``polar_iters`` per substep, for an
algorithm-for-algorithm comparison).

Taichi's runtime is process-global: :func:`init_taichi` must be called once per process, before the peer is built
(``threads=1`` gives a single-thread run comparable to Warp's single-thread CPU backend).
"""
from __future__ import annotations

import numpy as np

_INITIALISED: dict = {}


def init_taichi(threads: int | None = None, arch: str = "cpu") -> None:
    """Initialise Taichi once per process (CPU by default; ``threads`` = cpu_max_num_threads)."""
    import taichi as ti

    if _INITIALISED:
        if _INITIALISED.get("threads") != threads:
            raise RuntimeError("taichi is already initialised with a different thread count in this process")
        return
    kw = dict(arch=ti.cpu if arch == "cpu" else ti.cuda, default_fp=ti.f32, default_ip=ti.i32,
              offline_cache=True, log_level=ti.WARN)
    if threads is not None:
        kw["cpu_max_num_threads"] = int(threads)
    ti.init(**kw)
    _INITIALISED["threads"] = threads


def build_peer(positions: np.ndarray, n_grid: int, dx: float, dt: float, E: float, nu: float, rho: float,
               p_vol: float, gravity: float = -9.81, bound: int = 3, polar: str = "svd",
               velocities: np.ndarray | None = None, polar_iters: int = 1):
    """Create the peer (a data-oriented Taichi class) after :func:`init_taichi`."""
    import taichi as ti

    n = len(positions)
    mu0 = E / (2 * (1 + nu))
    lam0 = E * nu / ((1 + nu) * (1 - 2 * nu))
    p_mass = p_vol * rho
    inv_dx = 1.0 / dx
    use_quat = polar == "quat"
    if polar not in ("svd", "quat"):
        raise ValueError("polar must be 'svd' or 'quat'")

    @ti.data_oriented
    class TaichiMPM:
        def __init__(self):
            self.n = n
            self.x = ti.Vector.field(3, ti.f32, n)
            self.v = ti.Vector.field(3, ti.f32, n)
            self.C = ti.Matrix.field(3, 3, ti.f32, n)
            self.F = ti.Matrix.field(3, 3, ti.f32, n)
            self.q = ti.Vector.field(4, ti.f32, n)  # (x, y, z, w), only for polar="quat"
            self.grid_v = ti.Vector.field(3, ti.f32, (n_grid, n_grid, n_grid))
            self.grid_m = ti.field(ti.f32, (n_grid, n_grid, n_grid))
            self.x.from_numpy(np.asarray(positions, np.float32))
            self.reset()
            if velocities is not None:
                self.v.from_numpy(np.asarray(velocities, np.float32))

        @ti.kernel
        def reset(self):
            for p in self.x:
                self.v[p] = ti.Vector([0.0, 0.0, 0.0])
                self.C[p] = ti.Matrix.zero(ti.f32, 3, 3)
                self.F[p] = ti.Matrix.identity(ti.f32, 3)
                self.q[p] = ti.Vector([0.0, 0.0, 0.0, 1.0])

        @ti.func
        def quat_mat(self, q):
            x, y, z, w = q[0], q[1], q[2], q[3]
            return ti.Matrix([
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

        @ti.func
        def rotation(self, p, Fp):
            R = ti.Matrix.identity(ti.f32, 3)
            if ti.static(use_quat):
                # same warm-started Newton step on SO(3) as the Warp solver (constitutive.polar_rotation_quat)
                q = self.q[p]
                for _ in range(polar_iters):
                    R = self.quat_mat(q)
                    B = R.transpose() @ Fp
                    g = ti.Vector([B[2, 1] - B[1, 2], B[0, 2] - B[2, 0], B[1, 0] - B[0, 1]])
                    tr = B[0, 0] + B[1, 1] + B[2, 2]
                    H = tr * ti.Matrix.identity(ti.f32, 3) - 0.5 * (B + B.transpose())
                    d2 = H[0, 0] * H[1, 1] - H[0, 1] * H[0, 1]
                    dH = H.determinant()
                    om = ti.Vector([0.0, 0.0, 0.0])
                    if H[0, 0] > 0 and d2 > 0 and dH > 1e-12 * tr * tr * tr:
                        om = H.inverse() @ g
                    else:
                        om = g / (ti.abs(tr) + 1e-20)
                    w2 = om.dot(om)
                    if w2 < 1e-14:
                        break
                    if w2 > 1.0:
                        om = om / ti.sqrt(w2)
                    h = 0.5 * om
                    # q * dq, dq = (h, 1)  (x, y, z, w storage)
                    qv = ti.Vector([q[0], q[1], q[2]])
                    nv = q[3] * h + qv + qv.cross(h)
                    nw = q[3] - qv.dot(h)
                    q = ti.Vector([nv[0], nv[1], nv[2], nw]).normalized()
                R = self.quat_mat(q)
                self.q[p] = q
            else:
                U, sig, V = ti.svd(Fp)
                R = U @ V.transpose()
            return R

        @ti.kernel
        def substep(self):
            for I in ti.grouped(self.grid_m):
                self.grid_v[I] = ti.Vector([0.0, 0.0, 0.0])
                self.grid_m[I] = 0.0
            for p in self.x:
                Xp = self.x[p] * inv_dx
                base = ti.floor(Xp - 0.5).cast(ti.i32)
                fx = Xp - base.cast(ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
                Fp = self.F[p]
                R = self.rotation(p, Fp)
                J = Fp.determinant()
                tau = 2.0 * mu0 * (Fp - R) @ Fp.transpose() + ti.Matrix.identity(ti.f32, 3) * lam0 * J * (J - 1.0)
                affine = (-dt * p_vol * 4.0 * inv_dx * inv_dx) * tau + p_mass * self.C[p]
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    offset = ti.Vector([i, j, k])
                    dpos = (offset.cast(ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[k][2]
                    self.grid_v[base + offset] += weight * (p_mass * self.v[p] + affine @ dpos)
                    self.grid_m[base + offset] += weight * p_mass
            for I in ti.grouped(self.grid_m):
                m = self.grid_m[I]
                if m > 0:
                    vg = self.grid_v[I] / m
                    vg[2] += dt * gravity
                    for d in ti.static(range(3)):
                        if I[d] < bound and vg[d] < 0:
                            vg[d] = 0.0
                        if I[d] > n_grid - bound and vg[d] > 0:
                            vg[d] = 0.0
                    self.grid_v[I] = vg
            for p in self.x:
                Xp = self.x[p] * inv_dx
                base = ti.floor(Xp - 0.5).cast(ti.i32)
                fx = Xp - base.cast(ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
                new_v = ti.Vector.zero(ti.f32, 3)
                new_C = ti.Matrix.zero(ti.f32, 3, 3)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    offset = ti.Vector([i, j, k])
                    dpos = (offset.cast(ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[k][2]
                    gv = self.grid_v[base + offset]
                    new_v += weight * gv
                    new_C += 4.0 * inv_dx * inv_dx * weight * gv.outer_product(dpos)
                self.v[p] = new_v
                self.C[p] = new_C
                self.x[p] += dt * new_v
                self.F[p] = (ti.Matrix.identity(ti.f32, 3) + dt * new_C) @ self.F[p]

        def run(self, substeps: int):
            for _ in range(substeps):
                self.substep()
            ti.sync()

        def state_bytes(self) -> int:
            per = 4 * (3 + 3 + 9 + 9 + (4 if use_quat else 0))
            return per * n

    return TaichiMPM()


def main(argv: list[str] | None = None) -> None:
    """Subprocess entry used by ``flows.bench.mpm``: run the peer on a saved scene, print one JSON line."""
    import argparse
    import json
    import time

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", required=True, help=".npz with positions, velocities, n_grid, dx, dt, E, nu, rho, p_vol")
    ap.add_argument("--threads", type=int, default=0, help="cpu_max_num_threads (0 = taichi default)")
    ap.add_argument("--polar", default="svd", choices=["svd", "quat"])
    ap.add_argument("--polar-iters", type=int, default=1, help="quaternion iterations per substep (polar=quat)")
    ap.add_argument("--save", default=None, help="write the final positions to this .npy")
    ap.add_argument("--substeps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=3)
    a = ap.parse_args(argv)
    sc = np.load(a.scene)
    init_taichi(a.threads or None)
    import taichi as ti

    peer = build_peer(sc["positions"], int(sc["n_grid"]), float(sc["dx"]), float(sc["dt"]), float(sc["E"]),
                      float(sc["nu"]), float(sc["rho"]), float(sc["p_vol"]), gravity=float(sc["gravity"]),
                      bound=int(sc["bound"]), polar=a.polar, velocities=sc["velocities"], polar_iters=a.polar_iters)
    t0 = time.perf_counter()
    peer.run(a.warmup)  # JIT compile + warm caches (excluded from the throughput)
    compile_s = time.perf_counter() - t0
    times = []
    done = a.warmup
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        peer.run(a.substeps)
        times.append(time.perf_counter() - t0)
        done += a.substeps
    x = peer.x.to_numpy()
    n = len(x)
    if a.save:
        np.save(a.save, x)
    best = min(times)
    print(json.dumps(dict(
        solver="taichi", threads=a.threads or "default", polar=a.polar, n_particles=n, substeps=a.substeps,
        seconds=times, best_seconds=best, throughput=n * a.substeps / best, compile_seconds=compile_s,
        total_substeps=done, bytes_per_particle=peer.state_bytes() / n, com=x.mean(0).tolist(),
        x_min=x.min(0).tolist(), x_max=x.max(0).tolist(), finite=bool(np.isfinite(x).all()),
        taichi_version=".".join(map(str, ti.__version__)))))


if __name__ == "__main__":
    main()
