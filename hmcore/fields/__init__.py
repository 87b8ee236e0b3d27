"""Heterogeneous property fields: ensembles of PORO, PERM*, NTG per active cell, their priors
and the ES-MDA update (Emerick & Reynolds 2013), for history matching such as PUNQ-S3's
(Floris et al. 2001).

One concept per module, lowest first: :mod:`~hmcore.fields.spec` (a ``kind = "field"``
parameter and its prior, as the case file states them), :mod:`~hmcore.fields.ensemble` (the
``[ensemble]`` section), :mod:`~hmcore.fields.fieldset` (checks of a case's fields together,
the order they are drawn in), :mod:`~hmcore.fields.transform` (update space <-> physical
values), :mod:`~hmcore.fields.geometry` (cell centres from COORD/ZCORN or DX/DY),
:mod:`~hmcore.fields.grid` (a deck's grid read with opm.io), :mod:`~hmcore.fields.deck_edits`
(the deck's GRID copies a member's include comes after), :mod:`~hmcore.fields.zones`
(zones' cells, checks on the grid), :mod:`~hmcore.fields.covariance` (gstools models, exact
draws), :mod:`~hmcore.fields.prior` (drawn priors), :mod:`~hmcore.fields.grdecl` (a member's
INCLUDE file, GRDECL read back), :mod:`~hmcore.fields.realisations` (the user's GRDECL priors),
:mod:`~hmcore.fields.localisation` (distance tapers), :mod:`~hmcore.fields.layout` (fields and
scalars side by side in the smoother's matrix), :mod:`~hmcore.fields.smoother` (the batched
ES-MDA update, ask/tell), :mod:`~hmcore.fields.members` (an ensemble as a table of one column
per member; a member's run: its INCLUDE at the end of GRID, around the caller's simulator),
:mod:`~hmcore.fields.assimilation` (one ES-MDA run step by step: the prior, the data as the
smoother sees them, the update from the members' records), :mod:`~hmcore.fields.forecast`
(P90/P50/P10 of the prior and the posterior), :mod:`~hmcore.fields.spread` (the spread kept,
and a collapse against a known truth).

Free of Prefect and storage; it never starts a simulator (``members.MemberSimulator`` wraps
the one its caller gives). Nothing is imported here, so that reading a case file (``spec``)
does not load opm.io, gstools or the smoother.
"""
