"""The ES-MDA update of an ensemble of fields (and scalars), pure numpy in and out.

Ensemble smoother with multiple data assimilation (Emerick & Reynolds 2013, *Computers &
Geosciences* 55, 3-15): the prior ensemble is run, updated with the data whose error covariance
is inflated by ``alpha_1``, run again, updated with ``alpha_2``, ... with sum(1/alpha) = 1.
Each update is iterative_ensemble_smoother's (``ESMDA``; ``AdaptiveESMDA`` for correlation-
based localisation, Vossepoel, Evensen & van Leeuwen 2025; ``LocalizedESMDA`` with a
Gaspari-Cohn taper for distance-based localisation, :mod:`hmcore.fields.localisation`).

Shapes: ``X`` ``(members, parameters)`` float32 in update space (a field's active cells,
then the next field's, then any scalars: the caller's order), ``Y`` ``(members,
observations)`` the members' simulated data. The library works on ``(parameters, members)``;
the update is done in batches of parameters (``prepare_assimilation`` once, then
``assimilate_batch`` per batch), so that memory stays bounded whatever the grid.

A member whose run failed (``failed``), whose responses are not finite, or that was left out
before (a NaN row of ``X``) is left out of this update and every later one (ERT's way): its row
of the posterior is NaN. Fewer than ``min_realizations`` left: :class:`TooFewRealizations`.
A datum whose responses do not vary over the members that ran (a rate the well's control
sets, a quantity still zero before breakthrough) tells the update nothing and would make the
adaptive localisation's correlations 0/0: it is left out of that update (``Update.constant``).
The observation perturbations of iteration ``i`` come from ``default_rng([seed, i])``, drawn
for every member, so a member's perturbation does not depend on which others failed, and a
resumed iteration repeats the update exactly. Ask/tell: the smoother never runs a simulator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import iterative_ensemble_smoother as ies
import numpy as np

from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.localisation import distance_taper

SPREAD_TOLERANCE = 1e-9
"""A datum whose responses' standard deviation over the members is at most this share of its
observation error (``std``) is taken as constant and left out of the update."""
MAX_BATCH_BYTES = 256 * 2**20
"""Working memory of one batch of parameters (the default batch size is derived from it)."""


class TooFewRealizations(RuntimeError):
    """Fewer members ran than an update needs (the ensemble's ``min_realizations``)."""


@dataclass(frozen=True, eq=False)
class Observations:
    """The data: ``values`` and ``std`` ``(observations,)``; ``locations`` ``(observations,
    2)`` x, y of each datum for distance localisation (NaN rows: not localised)."""

    values: np.ndarray
    std: np.ndarray
    locations: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("values", "std", "locations"):  # arrays of float64 from any sequence
            if getattr(self, name) is not None:
                object.__setattr__(self, name, np.asarray(getattr(self, name), np.float64))
        n = np.shape(self.values)[0] if np.ndim(self.values) == 1 else -1
        if n < 1 or np.shape(self.std) != (n,):
            raise ValueError(f"values and std must be 1-D of one length, got "
                             f"{np.shape(self.values)} and {np.shape(self.std)}")
        if not (np.isfinite(self.values).all() and np.all(np.asarray(self.std) > 0)):
            raise ValueError("observations must be finite and their std > 0")
        if self.locations is not None and np.shape(self.locations) != (n, 2):
            raise ValueError(f"locations must have shape (observations, 2) = ({n}, 2), got "
                             f"{np.shape(self.locations)}")

    def subset(self, keep: np.ndarray) -> Observations:
        """The data where ``keep`` ``(observations,)`` is True."""
        return Observations(self.values[keep], self.std[keep],
                            None if self.locations is None else self.locations[keep])


@dataclass(frozen=True)
class SmootherSettings:
    """How the update runs (the case's :class:`~hmcore.fields.ensemble.EnsembleSpec`, plus
    the numerics): ``batch_size`` parameters per batch (None: from ``max_batch_bytes``);
    ``truncation`` the share of singular values kept in the inversion (Emerick 2013's 0.99);
    ``n_jobs`` the adaptive localisation's worker processes."""

    alphas: tuple[float, ...]
    min_realizations: int = 2
    localisation: str = "none"
    radius: float | None = None
    seed: int = 0
    batch_size: int | None = None
    max_batch_bytes: int = MAX_BATCH_BYTES
    truncation: float = 0.99
    n_jobs: int = 1

    @classmethod
    def of(cls, spec: EnsembleSpec, **numerics) -> SmootherSettings:
        """The settings of an ``[ensemble]`` section whose localisation is concrete (a case's
        is: ``localisation = "auto"`` is resolved with its fields when the case loads)."""
        if spec.localisation == "auto":
            raise ValueError("localisation 'auto' needs the case's fields to choose: use "
                             "EnsembleSpec.resolved(fields) first (a loaded case's ensemble is)")
        return cls(alphas=spec.alphas, min_realizations=spec.minimum,
                   localisation=spec.localisation, radius=spec.radius, seed=spec.seed,
                   **numerics)

    def batch(self, members: int, observations: int) -> int:
        """Parameters per batch: as given, else what fits ``max_batch_bytes`` (about
        ``8 * (2 * observations + 4 * members)`` bytes a parameter)."""
        if self.batch_size is not None:
            return max(1, self.batch_size)
        return max(1, self.max_batch_bytes // (8 * (2 * observations + 4 * members)))


@dataclass(frozen=True, eq=False)
class Update:
    """One assimilation's result: ``ensemble`` ``(members, parameters)`` float32, NaN rows for
    the members left out; ``active`` ``(members,)``; ``left_out`` the members left out at this
    step (failed or non-finite responses); ``iteration`` (0-based) and its ``alpha`` (the
    schedule normalised so that sum(1/alpha) = 1); ``batches`` of parameters; ``constant``
    the data left out because their responses did not vary over the members; ``seconds``."""

    ensemble: np.ndarray
    active: np.ndarray
    left_out: tuple[int, ...]
    iteration: int
    alpha: float
    batches: int
    seconds: float = field(compare=False)
    constant: tuple[int, ...] = ()


def assimilate(X: np.ndarray, Y: np.ndarray, observations: Observations, iteration: int,
               settings: SmootherSettings, failed: np.ndarray | None = None,
               locations: np.ndarray | None = None) -> Update:
    """The ES-MDA update number ``iteration`` (0-based) of ``X`` given the responses ``Y``
    (see the module's docstring). ``locations`` ``(parameters, 2)``: x, y of each parameter
    for distance localisation (NaN rows: not localised)."""
    started = time.perf_counter()
    X = np.asarray(X)
    Y = np.asarray(Y, dtype=np.float64)
    members, n_par = X.shape
    n_obs = observations.values.shape[0]
    if Y.shape != (members, n_obs):
        raise ValueError(f"Y must have shape (members, observations) = ({members}, {n_obs}), "
                         f"got {Y.shape}")
    if not 0 <= iteration < len(settings.alphas):
        raise ValueError(f"iteration must lie in 0..{len(settings.alphas) - 1} (one per "
                         f"inflation factor), got {iteration}")
    if failed is not None and np.shape(failed) != (members,):
        raise ValueError(f"failed must have shape (members,) = ({members},), got "
                         f"{np.shape(failed)}")
    before = ~np.isfinite(X).all(axis=1)
    now = np.zeros(members, bool) if failed is None else np.asarray(failed, bool).copy()
    now |= ~np.isfinite(Y).all(axis=1)
    now &= ~before
    active = ~(before | now)
    ok = np.flatnonzero(active)
    if ok.size < settings.min_realizations:
        raise TooFewRealizations(
            f"ES-MDA assimilation {iteration + 1} of {len(settings.alphas)}: {ok.size} of "
            f"{members} members have results ({int(now.sum())} failed now, {int(before.sum())} "
            f"left out before), fewer than min_realizations = {settings.min_realizations}; "
            "the iteration stops")
    noise = np.random.default_rng([settings.seed, iteration]).standard_normal((n_obs, members))
    varies = Y[ok].std(axis=0) > SPREAD_TOLERANCE * observations.std
    if not varies.any():
        raise ValueError(f"ES-MDA assimilation {iteration + 1}: none of the {n_obs} data varies "
                         f"over the {ok.size} members that ran; nothing to update from")
    used = observations if varies.all() else observations.subset(varies)
    smoother = _smoother(used, settings, iteration)
    perturbations = noise[np.ix_(varies, ok)] * used.std[:, None]
    smoother.prepare_assimilation(Y=np.ascontiguousarray(Y[np.ix_(ok, varies)].T),
                                  truncation=settings.truncation, overwrite=True,
                                  observation_perturbations=perturbations)
    posterior = np.full(X.shape, np.nan, dtype=np.float32)
    size = settings.batch(ok.size, n_obs)
    taper_xy = _check_locations(settings, used, locations, n_par)
    for start in range(0, n_par, size):
        stop = min(start + size, n_par)
        batch = np.ascontiguousarray(X[ok, start:stop].T, dtype=np.float32)
        if settings.localisation == "adaptive":
            new = smoother.assimilate_batch(X=batch, overwrite=True, n_jobs=settings.n_jobs)
        elif settings.localisation == "distance":
            rho = distance_taper(taper_xy[start:stop], used.locations, settings.radius)
            new = smoother.assimilate_batch(X=batch, overwrite=True,
                                            localization_callback=lambda K, rho=rho: K * rho)
        else:
            new = smoother.assimilate_batch(X=batch, overwrite=True)
        posterior[ok, start:stop] = new.T
    return Update(posterior, active, tuple(np.flatnonzero(now).tolist()), iteration,
                  float(smoother.alpha[iteration]), -(-n_par // size),
                  time.perf_counter() - started, tuple(np.flatnonzero(~varies).tolist()))


def _smoother(observations: Observations, settings: SmootherSettings, iteration: int):
    """The library's smoother, set to assimilation ``iteration`` of the schedule."""
    kinds = {"none": ies.ESMDA, "adaptive": ies.AdaptiveESMDA, "distance": ies.LocalizedESMDA}
    if settings.localisation not in kinds:
        raise ValueError(f"localisation must be one of {list(kinds)}, got "
                         f"{settings.localisation!r}")
    smoother = kinds[settings.localisation](
        covariance=np.asarray(observations.std, np.float64) ** 2,
        observations=np.asarray(observations.values, np.float64),
        alpha=np.asarray(settings.alphas, np.float64), seed=settings.seed)
    smoother.iteration = iteration - 1  # prepare_assimilation steps to `iteration`
    return smoother


def _check_locations(settings: SmootherSettings, observations: Observations,
                     locations: np.ndarray | None, n_par: int) -> np.ndarray | None:
    if settings.localisation != "distance":
        return None
    if settings.radius is None or not settings.radius > 0:
        raise ValueError(f"distance localisation needs radius > 0, got {settings.radius}")
    if observations.locations is None or locations is None:
        raise ValueError("distance localisation needs the observations' and the parameters' "
                         "locations")
    locations = np.asarray(locations, np.float64)
    if locations.shape != (n_par, 2):
        raise ValueError(f"locations must have shape (parameters, 2) = ({n_par}, 2), got "
                         f"{locations.shape}")
    return locations


class EnsembleSmoother:
    """ES-MDA as ask/tell: :meth:`ask` gives the members to run, :meth:`tell` takes their
    responses and updates. After the last update the ensemble is the posterior (run it once
    more for the forecast). State is the ensemble and the iteration, so a resumed flow builds
    one from its stored ensemble: ``EnsembleSmoother(X_i, ..., iteration=i)``."""

    def __init__(self, ensemble: np.ndarray, observations: Observations,
                 settings: SmootherSettings, locations: np.ndarray | None = None,
                 iteration: int = 0):
        self.ensemble = np.asarray(ensemble, dtype=np.float32)
        self.observations = observations
        self.settings = settings
        self.locations = locations
        self.iteration = iteration
        self.updates: list[Update] = []

    @property
    def done(self) -> bool:
        return self.iteration >= len(self.settings.alphas)

    @property
    def active(self) -> np.ndarray:
        """Members still in the ensemble ``(members,)``."""
        return np.isfinite(self.ensemble).all(axis=1)

    def ask(self) -> tuple[np.ndarray, np.ndarray]:
        """(member indices, their rows ``(runs, parameters)``) to run next."""
        index = np.flatnonzero(self.active)
        return index, self.ensemble[index]

    def tell(self, Y: np.ndarray, failed: np.ndarray | None = None) -> Update:
        """Responses ``(members, observations)`` of every member (rows of members not run are
        ignored) and the failed ones; updates the ensemble and steps the iteration."""
        if self.done:
            raise RuntimeError(f"all {len(self.settings.alphas)} assimilations are done")
        update = assimilate(self.ensemble, Y, self.observations, self.iteration,
                            self.settings, failed, self.locations)
        self.ensemble = update.ensemble
        self.iteration += 1
        self.updates.append(update)
        return update
