from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.policy.env import LinkModel, Retention, ScaleEnv
from zoffload.policy.mdp import DECREASE, INCREASE, KEEP, ScaleMDP

MDP = ScaleMDP()


def test_initial_state_and_actions_with_clamping() -> None:
    assert MDP.initial_state() == (0.0, 0.05)
    assert MDP.apply(0.05, DECREASE) == 0.03 and MDP.apply(0.05, KEEP) == 0.05
    assert MDP.apply(0.05, INCREASE) == 0.07
    assert MDP.apply(0.07, INCREASE) == 0.07  # clamped at the top
    assert MDP.apply(0.01, DECREASE) == 0.01 and MDP.apply(0.03, DECREASE) == 0.01  # and the bottom
    with pytest.raises(ValueError):
        MDP.apply(0.05, 3)


@pytest.mark.parametrize(
    "t, action, v, ratio, expected",
    [
        (0.10, DECREASE, 0.03, 0.8, 0.8),  # eq. 7: fast link, finer scans are rewarded
        (0.10, KEEP, 0.05, 0.6, 0.0),
        (0.10, INCREASE, 0.07, 0.4, -0.4),
        (0.20, DECREASE, 0.03, 0.8, -0.8),  # eq. 8: slow link, finer scans are punished
        (0.20, KEEP, 0.05, 0.6, (0.05 - 0.07) * 0.6 * 10),
        (0.20, KEEP, 0.07, 0.4, 0.0),  # keeping at v_max costs nothing
        (0.20, INCREASE, 0.07, 0.4, 0.0),
        (0.11, DECREASE, 0.03, 0.5, -0.5),  # T = 0.11 exactly is eq. 8
    ],
)
def test_every_reward_branch(t: float, action: int, v: float, ratio: float, expected: float) -> None:
    assert math.isclose(MDP.reward(t, action, v, ratio), expected, abs_tol=1e-12)


def test_out_of_range_state_is_clamped_not_raised() -> None:
    assert MDP.clamp_state(float("nan"), 0.5) == (0.0, 0.07)
    assert MDP.clamp_state(-3.0, -1.0) == (0.0, 0.01)
    assert MDP.clamp_state(1e9, float("nan")) == (60.0, 0.05)
    with pytest.raises(ValueError):
        ScaleMDP(v_min=0.08)


def recordings() -> list[dict[str, str]]:
    """Recorded-looking rows: 2 voxel sizes, a strong link (all on time) and a weak one (8 Mbps)."""
    rng = np.random.default_rng(0)
    rows = []
    for v, nbytes, kept in ((0.03, 260_000, 0.85), (0.07, 140_000, 0.45)):
        for link in (120.0, 8.0):
            for _ in range(40):
                t = max(0.1, nbytes * 8 / (link * 1e6)) + abs(rng.normal(0, 0.005))
                rows.append({"voxel": str(v), "bytes": str(nbytes), "n_sent": str(kept * 28000),
                             "n_raw": "28000", "interarrival": str(t), "link_up_mbps": str(link),
                             "status": "acked"})
    return rows


def test_models_fitted_from_recordings_drive_the_env() -> None:
    rows = recordings()
    ret = Retention.fit(rows)
    assert ret.at(0.05)[0] == pytest.approx(200_000) and ret.at(0.05)[1] == pytest.approx(0.65)
    link = LinkModel.fit(rows)
    assert len(link.levels) == 2
    assert link.levels[0].rate_mbps == pytest.approx(8.0, rel=0.05)  # the weak level's real rate
    env = ScaleEnv(MDP, ret, link, seed=1)
    # Weak link: 7 cm scans take ~0.14 s, so decreasing further is punished, increasing is neutral
    r_dec, (t, v) = env.step((0.2, 0.07), DECREASE, level=0)
    assert v == 0.05 and t > 0.11 and r_dec < 0
    r_inc, _ = env.step((0.2, 0.07), INCREASE, level=0)
    assert r_inc == 0.0
    # Strong link: everything on time, finer is rewarded
    r_fine, (t2, v2) = env.step((0.1, 0.05), DECREASE, level=1)
    assert v2 == 0.03 and t2 < 0.11 and r_fine == pytest.approx(0.85, rel=0.05)
    with pytest.raises(ValueError, match="two voxel sizes"):
        Retention.fit(rows[:40])
