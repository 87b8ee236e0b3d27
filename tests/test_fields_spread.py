"""The spread an ensemble keeps and the collapse rule (hmcore.fields.spread): pure numpy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmcore.fields.spread import COLLAPSED, FieldSpread, field_spread, spread


def test_a_truth_drawn_like_a_member_is_about_one_spread_from_the_mean():
    """Many cells, 100 members and a truth drawn from the same distribution: RMSE/spread near
    sqrt(1 + 1/100); the same members shrunk to a tenth around their mean, not moved: kept
    10 %, and the update collapsed them."""
    rng = np.random.default_rng(3)
    prior = rng.normal(0.0, 0.5, (100, 5000))
    truth = rng.normal(0.0, 0.5, 5000)
    shrunk = prior.mean(axis=0) + 0.1 * (prior - prior.mean(axis=0))
    s = field_spread("f", prior, shrunk, truth)
    assert s.error_to_spread[0] == pytest.approx(math.sqrt(1.01), rel=0.03)
    assert s.kept == pytest.approx(0.1, rel=1e-9) and s.prior_holds_truth and s.collapsed


def test_a_prior_that_misses_the_truth_is_not_called_collapsed_for_keeping_that_distance():
    """PUNQ-S3's first prior: its mean 2.6 spreads from the truth, the posterior's 3.4."""
    missed = FieldSpread("poro", 0.0333, 0.0242, 0.0853, 0.0828)
    assert not missed.prior_holds_truth and not missed.collapsed
    assert missed.error_to_spread[1] == pytest.approx(3.42, abs=0.01)
    doubled = FieldSpread("poro", 0.0333, 0.0242 / 3, 0.0853, 0.0828)  # surer, not closer
    assert doubled.collapsed and doubled.error_to_spread[1] > COLLAPSED * 2.56


def test_members_left_out_are_not_counted_and_unknowns_stay_unknown():
    X = np.array([[0.1, 0.2], [np.nan, np.nan], [0.3, 0.4]])
    assert spread(X) == pytest.approx(math.sqrt(0.02))
    unknown = field_spread("f", X, X)
    assert math.isnan(unknown.rmse_prior) and not unknown.collapsed and unknown.prior_holds_truth
    assert math.isnan(spread(X[:1]))  # one member: no spread
