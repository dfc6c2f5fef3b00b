"""Minimum s-t cut by Boykov and Kolmogorov's augmenting-path algorithm with two search trees.

Written from their paper (PAMI 2004, "An experimental comparison of min-cut/max-flow algorithms for
energy minimization in vision"): on the mask's 8-connected pixel grids it beats scipy's Dinic, which
rebuilds its level graph on every phase (bench/masks.py), and the libraries that wrap the authors' own
code are GPL. The answer is the same cut: the pixels reachable from the source once the
flow is maximal (`source_side`), the smallest minimum cut, which every maximum flow shares.

A graph is arcs in CSR order: node i's arcs are first[i]..first[i+1], arc a runs to head[a], and
sister[a] is the arc back (a pair of opposite arcs, each with its own capacity). Terminal edges are one
number a node, its source capacity minus its sink capacity: what both carry cancels into the flow at once.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

_FREE, _SOURCE_TREE, _SINK_TREE = 0, 1, 2  # which tree a node is in; a free node also has no parent
_NO_PARENT, _TERMINAL, _ORPHAN = -1, -2, -3
_FAR = 1 << 60


@njit(cache=True, _nrt=False)  # no reference counting of its four arrays on each of its many calls
def _root_distance(node, parent, head, stamp, distance, now):
    """Steps from `node` up its tree to the terminal, or _FAR if the path meets an orphan; marks the path."""
    steps = 0
    j = node
    while True:
        if stamp[j] == now:
            steps += distance[j]
            break
        arc = parent[j]
        steps += 1
        if arc == _TERMINAL:
            stamp[j] = now
            distance[j] = 1
            break
        if arc == _ORPHAN:
            return _FAR
        j = head[arc]
    j = node
    left = steps
    while stamp[j] != now:
        stamp[j] = now
        distance[j] = left
        left -= 1
        j = head[parent[j]]
    return steps


@njit(cache=True)
def max_flow(first, head, sister, residual, terminal):
    """The maximum flow's value. `residual` [arcs] and `terminal` [nodes], integer capacities, are left as
    the residual graph: pass copies to keep the capacities."""
    nodes = first.shape[0] - 1
    tree = np.zeros(nodes, np.int8)
    parent = np.full(nodes, _NO_PARENT, np.int64)
    stamp = np.zeros(nodes, np.int64)
    distance = np.zeros(nodes, np.int64)
    active = np.empty(nodes, np.int64)  # a ring buffer: each node is queued at most once at a time
    queued = np.zeros(nodes, np.bool_)
    orphans = np.empty(nodes, np.int64)  # a ring buffer too: a node is an orphan at most once at a time
    active_head, active_count = 0, 0
    flow = 0
    for i in range(nodes):
        if terminal[i] != 0:
            tree[i] = _SOURCE_TREE if terminal[i] > 0 else _SINK_TREE
            parent[i] = _TERMINAL
            distance[i] = 1
            active[(active_head + active_count) % nodes] = i
            active_count += 1
            queued[i] = True
    now = 0
    current = -1
    while True:
        if current < 0 or parent[current] == _NO_PARENT:
            current = -1
            while active_count > 0:
                i = active[active_head]
                active_head = (active_head + 1) % nodes
                active_count -= 1
                queued[i] = False
                if parent[i] != _NO_PARENT:
                    current = i
                    break
            if current < 0:
                break
        i = current
        # grow the active node's tree until it touches the other tree
        bridge = -1  # the arc from the source tree's side to the sink tree's
        for a in range(first[i], first[i + 1]):
            outward = a if tree[i] == _SOURCE_TREE else sister[a]
            if residual[outward] <= 0:
                continue
            j = head[a]
            if parent[j] == _NO_PARENT:
                tree[j] = tree[i]
                parent[j] = sister[a]
                stamp[j] = stamp[i]
                distance[j] = distance[i] + 1
                if not queued[j]:
                    active[(active_head + active_count) % nodes] = j
                    active_count += 1
                    queued[j] = True
            elif tree[j] != tree[i]:
                bridge = outward
                break
            elif stamp[j] <= stamp[i] and distance[j] > distance[i]:
                parent[j] = sister[a]  # a shorter way to the root: shallower trees adopt faster
                stamp[j] = stamp[i]
                distance[j] = distance[i] + 1
        now += 1
        if bridge < 0:
            current = -1
            continue
        # augment along source root -> ... -> tail --bridge--> tip -> ... -> sink root
        tail, tip = head[sister[bridge]], head[bridge]
        bottleneck = residual[bridge]
        j = tail
        while parent[j] != _TERMINAL:
            arc = parent[j]
            bottleneck = min(bottleneck, residual[sister[arc]])
            j = head[arc]
        bottleneck = min(bottleneck, terminal[j])
        j = tip
        while parent[j] != _TERMINAL:
            arc = parent[j]
            bottleneck = min(bottleneck, residual[arc])
            j = head[arc]
        bottleneck = min(bottleneck, -terminal[j])
        residual[bridge] -= bottleneck
        residual[sister[bridge]] += bottleneck
        orphan_head, orphan_count = 0, 0
        j = tail
        while True:
            arc = parent[j]
            if arc == _TERMINAL:
                terminal[j] -= bottleneck
                if terminal[j] == 0:
                    parent[j] = _ORPHAN
                    orphans[(orphan_head + orphan_count) % nodes] = j
                    orphan_count += 1
                break
            residual[arc] += bottleneck
            residual[sister[arc]] -= bottleneck
            if residual[sister[arc]] == 0:
                parent[j] = _ORPHAN
                orphans[(orphan_head + orphan_count) % nodes] = j
                orphan_count += 1
            j = head[arc]
        j = tip
        while True:
            arc = parent[j]
            if arc == _TERMINAL:
                terminal[j] += bottleneck
                if terminal[j] == 0:
                    parent[j] = _ORPHAN
                    orphans[(orphan_head + orphan_count) % nodes] = j
                    orphan_count += 1
                break
            residual[sister[arc]] += bottleneck
            residual[arc] -= bottleneck
            if residual[arc] == 0:
                parent[j] = _ORPHAN
                orphans[(orphan_head + orphan_count) % nodes] = j
                orphan_count += 1
            j = head[arc]
        flow += bottleneck
        # adopt each orphan into its tree again through a neighbour still rooted there, or free it
        while orphan_count > 0:
            i = orphans[orphan_head]
            orphan_head = (orphan_head + 1) % nodes
            orphan_count -= 1
            side = tree[i]
            best_arc, best_distance = -1, _FAR
            for a in range(first[i], first[i + 1]):
                inward = sister[a] if side == _SOURCE_TREE else a
                j = head[a]
                if residual[inward] <= 0 or tree[j] != side:
                    continue
                steps = _root_distance(j, parent, head, stamp, distance, now)
                if steps < best_distance:
                    best_arc, best_distance = a, steps
            if best_arc >= 0:
                parent[i] = best_arc
                stamp[i] = now
                distance[i] = best_distance + 1
                continue
            tree[i] = _FREE
            parent[i] = _NO_PARENT
            for a in range(first[i], first[i + 1]):
                j = head[a]
                if tree[j] != side:
                    continue
                inward = sister[a] if side == _SOURCE_TREE else a
                if residual[inward] > 0 and not queued[j]:
                    active[(active_head + active_count) % nodes] = j
                    active_count += 1
                    queued[j] = True
                arc = parent[j]
                if arc >= 0 and head[arc] == i:
                    parent[j] = _ORPHAN
                    orphans[(orphan_head + orphan_count) % nodes] = j
                    orphan_count += 1
    return flow


@njit(cache=True)
def source_side(first, head, residual, terminal):
    """[nodes] bool: reachable from the source in a maximum flow's residual graph (the smallest minimum cut)."""
    nodes = first.shape[0] - 1
    reached = np.zeros(nodes, np.bool_)
    queue = np.empty(nodes, np.int64)
    count = 0
    for i in range(nodes):
        if terminal[i] > 0:
            reached[i] = True
            queue[count] = i
            count += 1
    done = 0
    while done < count:
        i = queue[done]
        done += 1
        for a in range(first[i], first[i + 1]):
            j = head[a]
            if residual[a] > 0 and not reached[j]:
                reached[j] = True
                queue[count] = j
                count += 1
    return reached


def reference_cut(first: np.ndarray, head: np.ndarray, capacity: np.ndarray,
                  terminal: np.ndarray) -> tuple[int, np.ndarray]:
    """The peer the tests and bench/masks.py hold `max_flow` to: scipy's Dinic on the same graph (source n,
    sink n + 1), then the nodes the source reaches in its residual graph -> (flow, source side [nodes])."""
    n = first.size - 1
    rows = np.concatenate([np.repeat(np.arange(n), np.diff(first)), np.full(n, n), np.arange(n)])
    cols = np.concatenate([head, np.arange(n), np.full(n, n + 1)])
    caps = np.concatenate([capacity, np.maximum(terminal, 0), np.maximum(-terminal, 0)]).astype(np.int32)
    graph = sparse.csr_array((caps, (rows, cols)), shape=(n + 2, n + 2))  # parallel arcs summed
    graph.eliminate_zeros()  # the masks' arcs off the image: no capacity, to the pixel itself
    result = maximum_flow(graph, n, n + 1, method="dinic")
    residual = graph - result.flow
    residual.data = (residual.data > 0).astype(np.int32)
    residual.eliminate_zeros()
    side = np.zeros(n + 2, bool)
    side[breadth_first_order(residual, n, return_predecessors=False)] = True
    return int(result.flow_value), side[:n]
