"""The Gymnasium environment, the ask/tell proposers and the calibration loop (no simulator)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hmcore.calibration.methods import Feedback, RandomProposer, SACProposer, SACSettings, make_proposer
from hmcore.calibration.calls import Job
from hmcore.calibration.loop import best_record, calibrate
from hmcore.calibration.methods.env import HistoryMatchingEnv
from hmcore.cases import load_case
from hmcore.scoring.evaluation import Evaluation, Status, evaluate
from hmcore.model.parameters import ParameterSpace

SPACE = ParameterSpace.reference()
TARGET = np.array([0.3, -0.5, 0.6, -0.2, 0.1])


def quadratic_E(action) -> float:
    return float(np.mean((np.asarray(action) - TARGET) ** 2)) * 0.3 + 1e-3


def fake_evaluate(values: dict[str, float]) -> Evaluation:
    a = SPACE.to_action(values)
    if values["skin"] > 14.0:  # a "failed run" corner
        return Evaluation(values, Status.FAIL, float("nan"), 10.0, -10.0, reason="crash: fake")
    E = quadratic_E(a)
    return Evaluation(values, Status.COMPLETE, E, 0.0, -E, {"bhp": E}, 1.0, run_dir="/tmp/x")


def test_env_passes_gymnasium_and_sb3_checkers():
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    gym_check(HistoryMatchingEnv(SPACE, fake_evaluate), skip_render_check=True)
    sb3_check(HistoryMatchingEnv(SPACE, fake_evaluate), warn=True)


@pytest.mark.opm
def test_gymnasium_check_env_passes_with_the_real_opm_evaluator(small_case, tmp_path):
    """The paper's environment with the real simulator behind every step (the small synthetic
    case, conftest.small_case: the same five global parameters as PUNQ-S3's, a fraction of its
    run time)."""
    from gymnasium.utils.env_checker import check_env

    case = load_case(small_case)
    runs = itertools.count()

    def run(values):
        return evaluate(case, values, tmp_path / f"run{next(runs)}")

    check_env(HistoryMatchingEnv(case.space, run), skip_render_check=True)
    assert next(runs) >= 2  # it stepped the real simulator (twice with the same action at least)


def test_env_step_maps_action_to_bounds_and_reports_info():
    env = HistoryMatchingEnv(SPACE, fake_evaluate)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (SPACE.dim + 1,)
    action = np.array([1, -1, 0, 1, -1], dtype=np.float32)
    obs, reward, terminated, truncated, info = env.step(action)
    assert terminated and not truncated
    assert info["params"] == pytest.approx({"poro_mult": 1.2, "permx_mult": 0.3,
                                            "permy_mult": 1.65, "permz_mult": 3.0, "skin": -5.0})
    assert reward == pytest.approx(-info["E"] - info["penalty"])
    np.testing.assert_allclose(obs[:-1], action)          # a_prev
    assert obs[-1] == pytest.approx(info["E"])            # E_prev
    obs2, _ = env.reset()
    np.testing.assert_allclose(obs2, obs)                 # the next episode sees [a_prev, E_prev]


def test_failed_step_observes_penalty_and_negative_reward():
    env = HistoryMatchingEnv(SPACE, fake_evaluate)
    env.reset(seed=0)
    obs, reward, *_ , info = env.step(np.array([0, 0, 0, 0, 1.0], np.float32))
    assert info["status"] == "FAIL" and reward == -10.0 and obs[-1] == pytest.approx(10.0)


def test_action_value_round_trip():
    values = {"poro_mult": 0.9, "permx_mult": 2.0, "permy_mult": 0.5, "permz_mult": 1.0, "skin": 5.0}
    assert SPACE.to_values(SPACE.to_action(values)) == pytest.approx(values)
    assert SPACE.to_values(np.full(5, 7.0)) == pytest.approx(SPACE.to_values(np.ones(5)))  # clipped


def test_sb3_sac_learns_on_the_env_with_learn():
    """The reference route: SB3's own learn() loop on the env (a few steps, fake simulator)."""
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    model = SAC("MlpPolicy", HistoryMatchingEnv(SPACE, fake_evaluate), learning_rate=3e-4,
                buffer_size=10_000, batch_size=64, learning_starts=10, seed=0, device="cpu")
    model.set_logger(Logger(folder=None, output_formats=[]))  # SB3's default makes /tmp/SB3-*
    model.learn(total_timesteps=30)
    assert model.num_timesteps == 30


def _run(proposer, budget=60, workers=2, exploit_last=None):
    calls = []

    def batch(jobs: list[Job]) -> list[dict]:
        calls.append(len(jobs))
        out = []
        for j in jobs:
            ev = fake_evaluate(j.values)
            out.append({"index": j.index, "action": list(j.action), "params": j.values,
                        "status": ev.status.value, "E": ev.E, "penalty": ev.penalty,
                        "reward": ev.reward, "phase": j.phase})
        return out

    return calibrate(proposer, SPACE, batch, budget, workers, exploit_last=exploit_last), calls


def test_calibrate_counts_calls_in_batches_and_ends_on_exploit():
    records, calls = _run(RandomProposer(SPACE.dim, 0), budget=7, workers=3, exploit_last=True)
    assert calls == [3, 3, 1] and [r["index"] for r in records] == list(range(7))
    # random search's exploit point is one it simulated already: handed its record back
    # (calls.SimulatedPoints), it spends no call, and the last call is one more explore
    assert records[-1]["phase"] == "explore"
    assert len({tuple(np.round(r["action"], 9)) for r in records}) == 7  # no point twice
    # by default the proposer decides: random search's recommendation is a point it has
    # evaluated already (no call wasted on it), SAC's deterministic policy is not
    records, _ = _run(RandomProposer(SPACE.dim, 0), budget=7, workers=3)
    assert records[-1]["phase"] == "explore"
    records, _ = _run(SACProposer(SPACE.dim, 0, SACSettings(learning_starts=4)), budget=7)
    assert records[-1]["phase"] == "exploit"


def test_calibrate_replays_journaled_records_without_evaluating():
    first, _ = _run(RandomProposer(SPACE.dim, 0), budget=6, workers=2)
    done = {r["index"]: r for r in first[:4]}
    calls = []

    def batch(jobs):
        calls.extend(j.index for j in jobs)
        return [{"index": j.index, "action": list(j.action), "params": j.values, "status": "COMPLETE",
                 "E": 1.0, "penalty": 0.0, "reward": -1.0} for j in jobs]

    records = calibrate(RandomProposer(SPACE.dim, 0), SPACE, batch, 6, 2, done)
    assert calls == [4, 5] and records[:4] == first[:4]


def test_sac_is_reproducible_for_a_seed_and_beats_its_random_start():
    a, _ = _run(SACProposer(SPACE.dim, 3, SACSettings(learning_starts=20)), budget=60)
    b, _ = _run(SACProposer(SPACE.dim, 3, SACSettings(learning_starts=20)), budget=60)
    assert [r["action"] for r in a] == [r["action"] for r in b]
    c, _ = _run(SACProposer(SPACE.dim, 4, SACSettings(learning_starts=20)), budget=60)
    assert [r["action"] for r in a] != [r["action"] for r in c]
    warm = np.mean([r["E"] for r in a[:20] if math.isfinite(r["E"])])
    late = np.mean([r["E"] for r in a[-20:] if math.isfinite(r["E"])])
    assert late < warm  # the policy moved toward the optimum


def test_best_record_never_picks_failed_or_invalid():
    recs = [{"index": 0, "status": "FAIL", "E": float("nan"), "reward": -10},
            {"index": 1, "status": "INVALID", "E": 0.001, "reward": -5},
            {"index": 2, "status": "COMPLETE", "E": 0.2, "reward": -0.2},
            {"index": 3, "status": "COMPLETE", "E": 0.1, "reward": -0.1}]
    assert best_record(recs)["index"] == 3
    assert best_record(recs[:2]) is None


def test_make_proposer_rejects_unknown_agent():
    with pytest.raises(ValueError, match="agent must be one of"):
        make_proposer("ppo", 5, 0)
    assert isinstance(make_proposer("random", 5, 0), RandomProposer)


def test_feedback_for_failure_uses_penalty():
    from hmcore.calibration.loop import feedback_of

    assert feedback_of({"reward": -10.0, "E": None, "penalty": 10.0}) == Feedback(-10.0, 10.0, False)
    assert feedback_of({"reward": -0.5, "E": 0.4, "penalty": 0.1}) == Feedback(-0.5, 0.4, True,
                                                                               0.1)
    assert feedback_of({"reward": -0.5, "E": 0.4, "penalty": 0.1, "E_worst": 0.9}).worst == 0.9


def test_ablations_are_sac_with_one_setting_changed_and_learn_another_cost():
    """The judge (reward, E) is the same for every method; an ablation changes what the agent
    learns from: E without the penalty, or E + lambda x the worst well-response loss."""
    from hmcore.calibration.methods import ABLATIONS, METHODS, method_version

    assert set(ABLATIONS) <= set(METHODS) and all(b == "sac" for b, _ in ABLATIONS.values())
    assert {method_version(m) for m in ABLATIONS} == {method_version("sac")}
    robust, no_pen = make_proposer("sac-robust", 5, 0), make_proposer("sac-no-penalty", 5, 0)
    assert isinstance(robust, SACProposer) and robust.settings.robust_lambda == 0.5
    assert make_proposer("sac-replay-1", 5, 0).settings.gradient_steps == 1
    assert make_proposer("sac-ent-fixed", 5, 0).settings.ent_coef == 0.01
    penalised = Feedback(-0.5, 0.3, True, penalty=0.2, worst=0.8)
    failed = Feedback(-10.0, 10.0, False)
    default = make_proposer("sac", 5, 0)
    assert [default.cost_of(f) for f in (penalised, failed)] == [0.5, 10.0]
    assert no_pen.cost_of(penalised) == pytest.approx(0.3) and no_pen.cost_of(failed) == 10.0
    assert robust.cost_of(penalised) == pytest.approx(0.5 + 0.5 * 0.8)
    assert robust.cost_of(failed) == 10.0
    props = no_pen.ask(2)
    no_pen.tell(props, [penalised, Feedback(-0.4, 0.4)])
    np.testing.assert_allclose(no_pen.model.replay_buffer.rewards[:2, 0],
                               np.array([-0.3, -0.4]) * no_pen.settings.reward_scale, rtol=1e-6)


def test_sac_learns_from_failures_capped_at_the_worst_scored_cost():
    """A failed run's penalty (10) must not dwarf the E spread the critic has to learn."""
    from hmcore.calibration.methods.base import Proposal

    p = SACProposer(SPACE.dim, 0, SACSettings(learning_starts=4, failure_cost_factor=1.5,
                                              reward_transform="log", reward_scale=1.0))
    props = p.ask(4)
    p.tell(props, [Feedback(-0.2, 0.2), Feedback(-10.0, 10.0, False), Feedback(-0.6, 0.5),
                   Feedback(-0.1, 0.1)])
    np.testing.assert_allclose(p.learning_costs(), [0.2, 0.9, 0.6, 0.1])
    rewards = p.model.replay_buffer.rewards[:4, 0]
    # the critic learns -log(cost): 1.1x the floor and the floor stay 0.095 apart
    np.testing.assert_allclose(rewards, -np.log(p.learning_costs()) * p.settings.reward_scale,
                               rtol=1e-6)
    # a worse scored run raises the cap, and the buffered failure follows it
    p.tell([Proposal(props[0].action, props[0].observation, 0)], [Feedback(-2.0, 2.0)])
    assert p.learning_costs()[1] == pytest.approx(3.0)
    assert p.model.replay_buffer.rewards[1, 0] == pytest.approx(-np.log(3.0)
                                                                * p.settings.reward_scale)
    linear = SACProposer(SPACE.dim, 0, SACSettings(learning_starts=4, reward_transform="linear"))
    linear.tell(linear.ask(4), [Feedback(-0.2, 0.2), Feedback(-10.0, 10.0, False),
                                Feedback(-0.6, 0.5), Feedback(-0.1, 0.1)])
    np.testing.assert_allclose(linear.model.replay_buffer.rewards[:4, 0],
                               -linear.learning_costs() * linear.settings.reward_scale, rtol=1e-6)


# ----------------------------------------------------------------------------- sac-paper
def test_sac_paper_is_sb3_learn_over_the_env_with_the_papers_settings():
    """The published method: SB3's learn() steps HistoryMatchingEnv copies (one call per
    one-step episode), lr 3e-4, buffer 10,000, batch 64, SB3's defaults elsewhere."""
    from stable_baselines3 import SAC

    from hmcore.calibration.methods.sac_paper import BatchedEnv, PaperSAC

    p = make_proposer("sac-paper", SPACE.dim, 0)
    assert isinstance(p, PaperSAC)
    records, calls = _run(p, budget=120, workers=2)
    m = p.model
    assert isinstance(m, SAC) and isinstance(m.get_env(), BatchedEnv)
    assert all(isinstance(e, HistoryMatchingEnv) for e in m.get_env().envs)
    assert (m.learning_rate, m.buffer_size, m.batch_size) == (3e-4, 10_000, 64)
    default = SAC("MlpPolicy", HistoryMatchingEnv(SPACE, fake_evaluate), device="cpu")
    assert (m.learning_starts, m.tau, m.train_freq, m.ent_coef) == (
        default.learning_starts, default.tau, default.train_freq, default.ent_coef) == (
        100, 0.005, default.train_freq, "auto")
    assert m.policy.net_arch == default.policy.net_arch
    # one simulator call per transition, two at a time, every call a record in order
    assert calls == [2] * 60 and [r["index"] for r in records] == list(range(120))
    assert m.num_timesteps == 120
    # as many gradient steps as calls after the 100 uniform-random ones (the serial loop's 1:1)
    assert m._n_updates == 120 - 100
    # observation [a_prev, E_prev] of each copy; failed runs seen as their penalty
    last = m.get_env().envs[1]._obs
    np.testing.assert_allclose(last[:-1], records[-1]["action"], atol=1e-6)
    rec_e = records[-1]["E"] if math.isfinite(records[-1]["E"]) else records[-1]["penalty"]
    assert last[-1] == pytest.approx(min(rec_e, 10.0), rel=1e-6)


def test_sac_paper_resumes_by_replaying_the_journal_and_refuses_a_diverged_one():
    first, _ = _run(make_proposer("sac-paper", SPACE.dim, 5), budget=110, workers=2)
    done = {r["index"]: r for r in first[:104]}
    calls = []

    def batch(jobs):
        calls.extend(j.index for j in jobs)
        return [next(r for r in first if r["index"] == j.index) for j in jobs]

    again = calibrate(make_proposer("sac-paper", SPACE.dim, 5), SPACE, batch, 110, 2, done)
    assert calls == list(range(104, 110))  # nothing journaled is simulated again
    assert [r["action"] for r in again] == [r["action"] for r in first]
    # a journal from another seed is refused, not mixed
    other, _ = _run(make_proposer("sac-paper", SPACE.dim, 6), budget=4, workers=2)
    with pytest.raises(RuntimeError, match="diverged at call 0"):
        calibrate(make_proposer("sac-paper", SPACE.dim, 5), SPACE, batch, 110, 2,
                  {r["index"]: r for r in other})


def test_sac_paper_refuses_a_budget_that_is_not_a_multiple_of_the_workers():
    with pytest.raises(ValueError, match="multiple of workers"):
        _run(make_proposer("sac-paper", SPACE.dim, 0), budget=7, workers=2)


def test_trust_region_grows_on_successes_shrinks_on_failures_and_restarts():
    from hmcore.calibration.methods.trust_region import TrustRegion, TrustRegionSettings

    tr = TrustRegion(5, TrustRegionSettings(side_init=0.8, side_min=0.1))
    assert np.all(tr.bounds()[0] == -1) and np.all(tr.bounds()[1] == 1)  # nothing told yet
    a = np.zeros((2, 5))
    tr.update(a, np.array([1.0, 2.0]))           # first scored: centre set
    tr.update(a + 0.1, np.array([0.5, 3.0]))     # success 1
    tr.update(a + 0.2, np.array([0.25, 3.0]))    # success 2: doubled
    assert tr.side == pytest.approx(1.6) and tr.centre == pytest.approx(np.full(5, 0.2))
    lo, hi = tr.bounds()
    assert np.all(lo >= -1) and np.all(hi <= 1) and lo[0] == pytest.approx(-0.6)
    for _ in range(3):                           # ceil(max(4, 5) / 2) = 3 failures: halved
        tr.update(a, np.array([9.0, np.inf]))
    assert tr.side == pytest.approx(0.8)
    for _ in range(4 * 3):                       # 0.4, 0.2, 0.1, 0.05 < 0.1: restart
        tr.update(a, np.array([9.0, 9.0]))
    assert tr.restarts == 1 and tr.side == pytest.approx(0.8) and tr.best == 0.25


def test_sac_starts_on_sobol_points_then_proposes_apart_inside_its_trust_region():
    from scipy.stats import qmc

    from hmcore.calibration.methods.base import Proposal

    p = SACProposer(SPACE.dim, 3, SACSettings(learning_starts=4, start="sobol", candidates=512))
    first = np.stack([q.action for q in p.ask(4)])
    sobol = qmc.Sobol(SPACE.dim, scramble=True, seed=np.random.default_rng([3, 1]))
    np.testing.assert_allclose(first, sobol.random(4) * 2 - 1, rtol=1e-6)
    costs = [0.4, 0.2, 0.9, 0.6]
    p.tell([Proposal(a, np.zeros(SPACE.dim + 1, np.float32), i) for i, a in enumerate(first)],
           [Feedback(-c, c) for c in costs])
    lo, hi = p.region.bounds()
    assert np.allclose((lo + hi)[np.abs(first[1]) < 1 - p.region.side / 2] / 2,
                       first[1][np.abs(first[1]) < 1 - p.region.side / 2])  # centred on the best
    batch = np.stack([q.action for q in p.ask(3)])
    assert np.all(batch >= lo - 1e-6) and np.all(batch <= hi + 1e-6)
    gaps = [np.max(np.abs(batch[i] - batch[j])) for i in range(3) for j in range(i)]
    assert min(gaps) >= p.settings.spread * p.region.side - 1e-6
    rec = p.recommend()
    assert np.all(rec >= lo - 1e-6) and np.all(rec <= hi + 1e-6)
    assert not np.allclose(rec, first[1])  # never the incumbent again
