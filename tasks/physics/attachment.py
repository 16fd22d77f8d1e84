"""Whether the skin stayed on the object: the distance of each particle from the deformed body (issue: ruptured
skin opens locally and stays attached).

The deformed body at a frame is the largest cluster of the object's own particles (shell, ruptured shell, core:
everything but the released interior) linked wherever two lie within ``link`` of each other (default one grid cell
dx: such particles share most of their quadratic B-spline stencil, so the grid couples them).  A particle of that
cluster is at distance 0; any other at its distance to the nearest particle of the cluster, i.e. how far it lies
off the deformed object's surface.  Pure numpy / scipy.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def distance_from_body(positions: np.ndarray, body: np.ndarray, link: float) -> np.ndarray:
    """(particle,) m: each particle's distance from the deformed body (module doc).

    positions (particle, xyz) m; body (particle,) bool: the particles the object is made of (shell, ruptured
    shell, core); link m: the linking distance.  Released particles (not ``body``) are measured too."""
    x = np.asarray(positions, dtype=np.float64)
    body = np.asarray(body, dtype=bool)
    if x.ndim != 2 or x.shape[1] != 3 or body.shape != (len(x),) or not body.any() or not link > 0:
        raise ValueError(f"need positions (particle, 3), body (particle,) with a True and link > 0; got {x.shape}, "
                         f"{body.shape}, {link}")
    xb = x[body]
    pairs = cKDTree(xb).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xb), len(xb)))
    _, cluster = connected_components(graph, directed=False)
    main = cluster == np.bincount(cluster).argmax()
    return cKDTree(xb[main]).query(x)[0]


def detached_summary(positions: np.ndarray, labels: np.ndarray, body_labels: tuple[int, ...],
                     measured: dict[str, int], dx: float, cells: float = 3.0) -> dict[str, float | None]:
    """How much of each ``measured`` label (name -> label) lies more than ``cells`` grid cells (dx m) off the body
    made of ``body_labels``: ``{name}_detached`` the fraction (None without such particles) and ``max_distance`` m
    over all measured particles."""
    labels = np.asarray(labels)
    dist = distance_from_body(positions, np.isin(labels, body_labels), dx)
    out: dict[str, float | None] = {"cells": float(cells)}
    for name, lab in measured.items():
        sel = labels == lab
        out[f"{name}_detached"] = float((dist[sel] > cells * dx).mean()) if sel.any() else None
    sel = np.isin(labels, list(measured.values()))
    out["max_distance"] = float(dist[sel].max()) if sel.any() else 0.0
    return out
