"""The split error constants are measured data: regenerating one row of
``split_constants.json`` with the recorded settings reproduces it."""

from __future__ import annotations

import json
from importlib import resources as importlib_resources

import pytest
import torch

from subslope.render import nearfar
from subslope.validation.split_constants import class_rows, constant_classes, round_significant


def _doc():
    return json.loads(
        (importlib_resources.files("subslope") / "render" / "split_constants.json").read_text()
    )


def test_file_records_its_provenance_and_matches_the_module():
    doc = _doc()
    prov = doc["provenance"]
    assert (
        prov["script"] == "benchmarks/split_constants.py" and prov["seeds"] and prov["members"] > 0
    )
    assert tuple(doc["rho_ladder"]) == nearfar.RHO_LADDER
    assert tuple(doc["epl_gamma_edges"]) == nearfar.EPL_GAMMA_EDGES
    n_classes = {"epl": len(nearfar.EPL_GAMMA_EDGES) + 1, "nfw": 1, "tnfw": 1}
    for where in ("interior", "edge"):
        for profile, by_order in doc[where].items():
            for order, rows in by_order.items():
                assert len(rows) == n_classes[profile] and all(
                    len(r) == len(nearfar.RHO_LADDER) for r in rows
                )
                assert all(v > 0 for r in rows for v in r), (where, profile, order)


@pytest.mark.usefixtures("one_thread")
def test_regenerating_one_row_reproduces_the_file():
    """The NFW class on the image grid (edge case), every order, every recorded seed."""
    doc = _doc()
    prov = doc["provenance"]
    index = [p for p, _ in constant_classes(nearfar.EPL_GAMMA_EDGES)].index("nfw")
    best: dict[int, list[float]] = {}
    for seed in prov["seeds"]:
        for where, profile, row, order, values in class_rows(
            members=prov["members"],
            spacing=prov["spacing"],
            grid=prov["grid"],
            safety=prov["safety"],
            seed=seed,
            rho_ladder=nearfar.RHO_LADDER,
            gamma_edges=nearfar.EPL_GAMMA_EDGES,
            only=("edge", index),
        ):
            assert (where, profile, row) == ("edge", "nfw", 0)
            best[order] = [max(a, b) for a, b in zip(best.get(order, [0.0] * len(values)), values)]
    assert sorted(best) == [4, 6, 8]
    for order, values in best.items():
        got = [round_significant(v, prov["round_digits"]) for v in values]
        assert got == doc["edge"]["nfw"][str(order)][0], order
        # the renderer reads exactly these numbers
        want = torch.as_tensor(nearfar.EDGE_ERROR_CONSTANTS["nfw"][order][0], dtype=torch.float64)
        torch.testing.assert_close(torch.as_tensor(got, dtype=torch.float64), want, rtol=0, atol=0)
