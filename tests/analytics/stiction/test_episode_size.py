"""S read off the stick-jump episodes (analytics/stiction/episode_size.py), against the
simulated valves' S and against the Hammerstein estimate on the same windows."""

import numpy as np
import pytest

from analytics.diagnosis import diagnose_loop
from analytics.stiction.episode_size import (
    EPISODE_S_ERROR,
    EpisodeSize,
    compare_sizes,
    episode_size,
)
from analytics.stiction.stick_jump import StickEpisode
from analytics.synthetic_cases import synthetic_library

CYCLES = ("flow-kano-S4-J2-ts1", "flow-he-S8-J2-ts1", "flow-he-S2-J1-ts0.5",
          "level-kano-S2-J1-ts1")


@pytest.fixture(scope="module")
def cycles():
    cases = {c.name: c for c in synthetic_library()}
    found = {}
    for name in CYCLES:
        case = cases[name]
        r = case.simulate()
        found[name] = (case, diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0],
                                           process_type=case.process_type))
    return found


@pytest.mark.parametrize("name", CYCLES)
def test_on_a_stiction_cycle_the_episodes_give_the_simulated_s(cycles, name):
    case, diagnosis = cycles[name]
    sized = diagnosis.episode_size
    assert sized is not None and sized.S is not None and sized.reversals >= 2
    assert pytest.approx(case.S, rel=EPISODE_S_ERROR) == sized.S
    # The hold's own OP travel misses the band's first part (PV still settling): it reads
    # low, while the travel from OP's turn does not.
    assert diagnosis.episode_stick_band < 0.85 * case.S


@pytest.mark.parametrize("name", CYCLES)
def test_the_episodes_and_the_hammerstein_estimate_agree_on_a_simulated_valve(cycles, name):
    _, diagnosis = cycles[name]
    assert diagnosis.size_comparison is not None
    assert diagnosis.size_comparison.agree, diagnosis.size_comparison.note
    assert "the episodes agree" in diagnosis.size_comparison.note
    assert diagnosis.to_dict()["stiction"]["episode_size"]["agrees_with_hammerstein"] is True


def _episode(start: int, jump_at: int, travel: float) -> StickEpisode:
    return StickEpisode(start, jump_at + 2, jump_at, travel, travel, 0.0, True)


def test_travel_counts_from_ops_turn_not_from_the_hold_start():
    # OP ramps up to 3, turns and ramps down 4 before the valve slips at sample 160 (a
    # reversal); then it goes on down 1 more and slips again (no reversal: J-like).
    op = np.concatenate([np.linspace(0, 3, 60), np.linspace(3, -1, 100),
                         np.linspace(-1, -2, 40)])
    episodes = [_episode(20, 59, 3.0), _episode(100, 159, -2.5), _episode(170, 199, -0.8)]
    sized = episode_size(op, episodes)
    assert sized is not None
    assert sized.reversals == 1 and sized.same_direction == 2
    assert pytest.approx(4.0, abs=0.05) == sized.S  # from the turn at 3 to the slip at -1
    assert sized.S_range == (sized.S, sized.S)
    assert sized.same_direction_band is not None and sized.same_direction_band < sized.S


def test_without_episodes_there_is_no_size():
    assert episode_size(np.zeros(10), []) is None


def test_the_comparison_allows_the_episodes_error_beyond_the_interval():
    sized = EpisodeSize(4.3, (4.1, 4.5), 3, None, 0)
    inside = compare_sizes(sized, 4.0, (3.9, 4.0 / (1 - EPISODE_S_ERROR) * 1.0))
    assert inside is not None and inside.agree
    high = compare_sizes(EpisodeSize(6.0, (5.8, 6.2), 3, None, 0), 4.0, (3.8, 4.2))
    assert high is not None and not high.agree
    assert "more OP travel than the fitted model" in high.note
    low = compare_sizes(EpisodeSize(2.0, (1.9, 2.1), 3, None, 0), 4.0, (3.8, 4.2))
    assert low is not None and not low.agree and "less OP travel" in low.note
    assert compare_sizes(EpisodeSize(None, None, 0, 1.0, 2), 4.0, (3.8, 4.2)) is None
