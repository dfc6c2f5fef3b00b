"""The mask's max-flow: the same flow and the same cut, the smallest minimum cut, as scipy's Dinic
(`maxflow.reference_cut`), on graphs built to be hard."""

from __future__ import annotations

import numpy as np
import pytest

from station.process import maxflow


def random_graph(rng: np.random.Generator, nodes: int, pairs: int, terminal_range: int, arc_range: int):
    """Arcs in pairs (a, a ^ 1 are sisters, each with its own capacity), sorted into CSR; terminals mixed."""
    tail = rng.integers(0, nodes, pairs)
    tip = (tail + rng.integers(1, nodes, pairs)) % nodes  # no self-loops
    ends = np.stack([np.stack([tail, tip], 1), np.stack([tip, tail], 1)], 1).reshape(-1, 2)  # [2 pairs, 2]
    capacity = rng.integers(0, arc_range + 1, 2 * pairs)
    order = np.argsort(ends[:, 0], kind="stable")
    position = np.empty_like(order)
    position[order] = np.arange(order.size)
    first = np.searchsorted(ends[order, 0], np.arange(nodes + 1)).astype(np.int32)
    head = ends[order, 1].astype(np.int32)
    sister = position[order ^ 1].astype(np.int32)
    terminal = rng.integers(-terminal_range, terminal_range + 1, nodes).astype(np.int32)
    return first, head, sister, capacity[order].astype(np.int32), terminal


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("shape", ["sparse, wide capacities", "dense, tied capacities", "terminals only"])
def test_the_flow_and_cut_match_scipy_on_random_graphs(seed: int, shape: str) -> None:
    rng = np.random.default_rng(seed)
    nodes, pairs, terminal_range, arc_range = {"sparse, wide capacities": (200, 400, 1000, 1000),
                                               "dense, tied capacities": (60, 900, 3, 2),
                                               "terminals only": (30, 1, 5, 0)}[shape]
    first, head, sister, capacity, terminal = random_graph(rng, nodes, pairs, terminal_range, arc_range)
    best, smallest = maxflow.reference_cut(first, head, capacity, terminal)

    residual, left = capacity.copy(), terminal.copy()
    flow = maxflow.max_flow(first, head, sister, residual, left)

    assert flow == best
    assert (residual >= 0).all() and (residual + residual[sister] == capacity + capacity[sister]).all()
    np.testing.assert_array_equal(maxflow.source_side(first, head, residual, left), smallest)


def test_a_graph_with_no_terminal_capacity_carries_no_flow() -> None:
    first, head, sister, capacity, _ = random_graph(np.random.default_rng(0), 20, 40, 0, 9)
    terminal = np.zeros(20, np.int32)
    assert maxflow.max_flow(first, head, sister, capacity.copy(), terminal) == 0
    assert not maxflow.source_side(first, head, capacity, terminal).any()


def test_a_long_chain_is_cut_at_its_weakest_arc() -> None:
    """One path through many nodes: the trees grow deep and every augmentation orphans a subtree."""
    n = 5000
    weights = np.random.default_rng(1).integers(5, 100, n - 1)
    weights[3210] = 2
    tail = np.arange(n - 1)
    ends = np.stack([np.stack([tail, tail + 1], 1), np.stack([tail + 1, tail], 1)], 1).reshape(-1, 2)
    capacity = np.stack([weights, np.zeros_like(weights)], 1).ravel()
    order = np.argsort(ends[:, 0], kind="stable")
    position = np.empty_like(order)
    position[order] = np.arange(order.size)
    first = np.searchsorted(ends[order, 0], np.arange(n + 1)).astype(np.int32)
    terminal = np.zeros(n, np.int32)
    terminal[0], terminal[-1] = 1000, -1000
    residual = capacity[order].astype(np.int32)

    flow = maxflow.max_flow(first, ends[order, 1].astype(np.int32), position[order ^ 1].astype(np.int32), residual,
                            terminal)

    assert flow == 2
    side = maxflow.source_side(first, ends[order, 1].astype(np.int32), residual, terminal)
    assert side[:3211].all() and not side[3211:].any()
