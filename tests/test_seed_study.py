"""The first seed's reproduction study: its verdict follows the data, and it runs."""

import numpy as np
import pandas as pd
import pytest

from studies import seed_sps


def table(g_seed, status="ok", h_ok=(0.5, 0.1)):
    """A hand-made ``runs`` table: the seed's scheme at h = 0.5 with ``status`` and max
    |g| ``g_seed``, and finished runs at the other steps in ``h_ok``."""
    rows = [dict(integrator="lobatto3ab2", h=0.5, status=status, steps=100 if status == "ok"
                 else 1, reached=50.0 if status == "ok" else 0.5, max_g=g_seed,
                 message="" if status == "ok" else "Newton failed")]
    rows += [dict(integrator="lobatto3ab2", h=h, status="ok", steps=int(50 / h), reached=50.0,
                  max_g=1e-15, message="") for h in h_ok if h != 0.5]
    return pd.DataFrame(rows)


def test_the_verdict_follows_the_data():
    assert "support the claim" in seed_sps.verdict(table(1e-12))
    assert "contradict the claim" in seed_sps.verdict(table(1e-8))
    failed = seed_sps.verdict(table(np.nan, status="failed"))
    assert "not reproduced" in failed and "h = 0.1" in failed
    assert "not checked" in seed_sps.verdict(table(1e-12).query("h != 0.5"))
    assert "No 2-stage run completed" in seed_sps.verdict(
        table(np.nan, status="failed", h_ok=()))


@pytest.mark.slow
def test_the_study_writes_its_tables_and_figures(tmp_path):
    """The study runs the seed's setting: the 2-stage scheme fails at h = 0.5 in its
    second step (the same failure RATTLE, the same map, shows in tests/test_spark.py), the
    verdict says so, the radii keep the seed's bar length at every snapshot, and both
    figures are written."""
    tables = seed_sps.run(tmp_path)
    runs = tables["runs"]
    assert set(runs["integrator"]) == {"lobatto3ab2", "rattle"}
    assert (runs.loc[runs["status"] == "ok", "max_g"] <= 1e-12).all()
    snaps = tables["snapshots"]
    assert len(snaps) == len(seed_sps.SNAPSHOT_TIMES)
    # The seed's geometry: bars of length l between radii R and r at an angular offset of
    # pi/6, l^2 = 1 + 0.64 - 1.6 cos(pi/6) for R0 = 1, r0 = 0.8.
    l2 = 1.64 - 0.8 * np.sqrt(3.0)
    assert np.all(np.abs(snaps["R"] ** 2 + snaps["r"] ** 2 - np.sqrt(3.0) * snaps["R"]
                         * snaps["r"] - l2) <= 1e-12)
    assert snaps["R"].nunique() > 1  # the receiver deploys
    assert (tmp_path / "fig3_positions.svg").stat().st_size > 0
    assert (tmp_path / "fig4_violation.svg").stat().st_size > 0
    seed = runs[(runs["integrator"] == "lobatto3ab2") & (runs["h"] == 0.5)].iloc[0]
    assert seed["status"] == "failed" and seed["steps"] == 1
    assert "not reproduced" in tables["claim"]["verdict"].iloc[0]
