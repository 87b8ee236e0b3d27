"""``hmflow hide`` and ``hmflow reveal``: write a case that hides an effect, then judge a
diagnosis of it (:mod:`hmcore.scenarios.hide`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from hmflow.cli.common import (
    DEFAULT_STORAGE,
    GENERATORS_HELP,
    app,
    console,
    fail,
    load_case,
    num,
    parse_sets,
    refuse,
)

FIELD_KIND = "field"
"""``--kind field``: a truth of a case's field parameters (:mod:`hmcore.scenarios.field_truth`);
spelled here so that ``--help`` does not import it."""


@app.command()
def hide(out: Path = typer.Option(..., "--out", help="New directory for the case (must not "
                                  "exist or be empty)"),
         kind: Optional[str] = typer.Option(None, "--kind", help="Kind of the hidden effect, "
                                            "drawn by --seed: a library kind, or a generator "
                                            f"of effects beyond the library ({GENERATORS_HELP}"
                                            "); 'field': a truth drawn from the field prior of "
                                            "--case; omit: a control, nothing hidden"),
         case: Optional[str] = typer.Option(None, "--case", help="With --kind field: the case "
                                            "TOML whose field prior the truth is drawn from"),
         seed: int = typer.Option(0, "--seed", help="Draws the effect, its strength and the "
                                  "noise (and, for the synthetic case, the fields)"),
         candidate: Optional[str] = typer.Option(None, "--candidate", help="Hide this library "
                                                 "candidate instead of drawing one, e.g. "
                                                 "'regional_permeability:PROD2'"),
         value: Optional[float] = typer.Option(None, "--value", help="Its value (default: drawn "
                                               "from the kind's realistic range)"),
         deck: Optional[Path] = typer.Option(None, "--deck", help="Base deck (default: the "
                                             "built-in synthetic reservoir of --seed)"),
         set_: list[str] = typer.Option([], "--set", help="NAME=VALUE of the five global "
                                        "parameters in the truth (with --deck; default "
                                        "multipliers 1, the deck's skin)"),
         history_end: Optional[float] = typer.Option(None, "--history-end", help="Days fitted "
                                                     "(default: 75 % of the record)"),
         record_end: Optional[float] = typer.Option(None, "--record-end", help="Last day of the "
                                                    "measured record (default: the schedule's "
                                                    "end; with --deck)"),
         sigma: bool = typer.Option(False, "--sigma/--no-sigma", help="Write the noise sigma "
                                    "into the CSV (default: no, the diagnosis estimates it)")
         ) -> None:
    """Write a case whose "measured" history hides one model extension the base model lacks
    (the truth run + realistic correlated noise), to try `hmflow diagnose` on, then `hmflow
    reveal` to see whether it found it. The effect is recorded in OUT/hidden_effect.json.
    With --kind field --case C: a truth of C's field parameters, recorded in
    OUT/hidden_truth.json, to try `hmflow ensemble` on."""
    if kind == FIELD_KIND:
        others = {"--candidate": candidate is not None, "--value": value is not None,
                  "--deck": deck is not None, "--set": bool(set_),
                  "--history-end": history_end is not None,
                  "--record-end": record_end is not None, "--sigma": sigma}
        return _hide_field(out, case, seed, [k for k, given in others.items() if given])
    refuse([f"--case {case}: only with --kind field (other kinds use --deck)"]
           if case is not None else [])
    # the scenarios import pandas and the simulator: keeps `hmflow --help` fast
    from hmcore.model.parameters import ParameterSpace
    from hmcore.scenarios.hide import hide_case, hide_problems

    refuse(hide_problems(out, kind=kind, candidate=candidate, value=value, deck=deck,
                         globals_given=bool(set_), record_end_days=record_end))
    truth_globals = parse_sets(set_, ParameterSpace.reference().names) if deck is not None else {}
    try:
        made = hide_case(out, seed=seed, kind=kind, candidate=candidate, value=value,
                         deck=deck, globals_=truth_globals, history_end_days=history_end,
                         record_end_days=record_end, with_sigma=sigma)
    except ValueError as exc:
        fail(str(exc))
    n = made.n_effects
    what = ("nothing (a control)" if made.effect is None else
            f"one {made.effect.kind} effect" if n == 1 else f"{n} effects")
    if made.generator and kind == made.generator:
        what += f", generated by {kind} (beyond the library's own geometry)"
    for line in (f"[green]Case written[/]: {made.case_toml}",
                 (f"  hidden: {what}; the details are in {made.hidden_json} (look after "
                  "diagnosing)"),
                 *([f"  signal: {signal_text(made.signal)}"] if made.signal else []),
                 f"  next:   hmflow diagnose --case {made.case_toml}",
                 (f"          hmflow reveal --hidden {made.hidden_json} --diagnosis <the "
                  "diagnosis.json it prints>")):
        console.print(line, soft_wrap=True, highlight=False)


def _hide_field(out: Path, case: Optional[str], seed: int, others: list[str]) -> None:
    """``hide --kind field``: every problem of the request refused, one line each, before the
    truth is drawn or run; then the truth run and the case."""
    refuse([f"{o}: not for --kind field (the truth is drawn from the prior of --case)"
            for o in others] + ([] if case else [("--kind field needs --case (a case TOML "
                                                   "with kind = \"field\" parameters)")]))
    # the field truth imports the simulator and pandas: keeps `hmflow --help` fast
    from hmcore.scenarios.field_truth import field_truth_problems, hide_field_truth, out_problems

    loaded = load_case(case)
    refuse(out_problems(out) + field_truth_problems(loaded))
    try:
        made = hide_field_truth(loaded, out, seed)
    except ValueError as exc:
        fail(str(exc))
    for line in (f"[green]Case written[/]: {made.case_toml}",
                 (f"  hidden: a truth of the fields of {loaded.source}, seed {seed}; FOPT at the "
                  f"schedule's end and the truth's files in {made.hidden_json} (look after "
                  "the ensemble)"),
                 (f"  observed: {made.observed_rows} rows to day {made.history_end_days:g}, "
                  "PUNQ-S3's noise, no sigma"),
                 f"  next:   hmflow ensemble --case {made.case_toml} --campaign NAME",
                 f"          hmflow reveal --hidden {made.hidden_json} --campaign NAME"):
        console.print(line, soft_wrap=True, highlight=False)


@app.command()
def reveal(hidden: Path = typer.Option(..., "--hidden", help="hidden_effect.json of a case "
                                       "written by `hmflow hide` (or hidden_truth.json of "
                                       "`hmflow hide --kind field`)"),
           diagnosis: Optional[Path] = typer.Option(None, "--diagnosis", help="diagnosis.json "
                                                    "written by `hmflow diagnose`"),
           campaign: Optional[str] = typer.Option(None, "--campaign", help="With a "
                                                  "hidden_truth.json: the `hmflow ensemble` "
                                                  "run on its case"),
           storage: Path = typer.Option(DEFAULT_STORAGE, "--storage", help="Artifact store of "
                                        "--campaign")) -> None:
    """Compare a diagnosis with the effect hidden in its case: right kind and well / layer
    ranked first, selected, held-back misfit improved. Exit 1 when it was not found.
    With --campaign: an ensemble run against its hidden field truth (the truth's forecast in
    the prior's and the posterior's P10-P90, the mean fields' RMSE); exit 1 when the truth's
    FOPT lies outside the posterior's P10-P90."""
    refuse([f"{label} {path}: no such file"
            for label, path in (("--hidden", hidden), ("--diagnosis", diagnosis))
            if path is not None and not path.is_file()]
           + ([("give --diagnosis (a hidden effect) or --campaign (a hidden field truth), one "
                "of them")] if (diagnosis is None) == (campaign is None) else []))
    if campaign is not None:
        return _reveal_field(hidden, storage, campaign)
    # the judging imports the diagnosis (pandas): keeps `hmflow --help` fast
    from hmcore.scenarios.hide import reveal as judged

    r = judged(hidden, diagnosis)
    if r.several:
        _print_effects(r)
    else:
        _print_effect(r)
    console.print("[bold green]FOUND[/]" if r.found else "[bold red]NOT FOUND[/]")
    j = r.verdict  # the answer by the evidence (issue 46): right, honest or wrong
    console.print(f"by the evidence: {j['outcome'].upper()} (answer of {j['set_size']}: "
                  f"{', '.join(j['members']) or '-'})", highlight=False)
    if not r.found:
        raise typer.Exit(1)


def _reveal_field(hidden: Path, storage: Path, campaign: str) -> None:
    """``reveal --campaign``: the truth's quantities against the bands, the fields' RMSE."""
    from hmcore.scenarios.field_truth import reveal_field_truth

    try:
        r = reveal_field_truth(hidden, storage, campaign)
    except (ValueError, OSError, KeyError) as exc:
        fail(str(exc))
    console.print(f"ensemble {campaign} against the truth of {hidden} (P90 <= truth <= P10):",
                  highlight=False)
    for c in r.checks:
        mark = ("[green]inside[/]" if c.inside else "[red]outside[/]") + (
            " (one value: the wells' controls fix it, not the fields)" if c.width < 1e-4 else "")
        console.print(f"  {c.ensemble:9s} {c.well} {c.quantity}: truth {c.truth:.5g}, "
                      f"P90/P50/P10 {c.P90:.5g}/{c.P50:.5g}/{c.P10:.5g} ({c.members} members, "
                      f"{c.width:.1%} wide) {mark}", highlight=False, soft_wrap=True)
    for e in ("prior", "posterior"):
        n = sum(c.inside for c in r.checks if c.ensemble == e)
        total = sum(c.ensemble == e for c in r.checks)
        console.print(f"{e}: {n} of {total} quantities inside P10-P90", highlight=False)
    for e in r.errors:
        ratio = e.error_to_spread
        console.print(f"field {e.field} ({e.space}): RMSE of the mean to the truth, prior "
                      f"{e.rmse_prior:.4g} -> posterior {e.rmse_posterior:.4g}; the members' spread "
                      f"{e.sd_prior:.4g} -> {e.sd_posterior:.4g}; RMSE/spread {ratio[0]:.2f} "
                      f"-> {ratio[1]:.2f}" + (
                          " [red](collapsed: the update made it surer than it is right)[/]"
                          if e.collapsed else "") + (
                          "" if e.prior_holds_truth else " (the prior misses the truth)"),
                      highlight=False, soft_wrap=True)
    console.print("[bold green]FOPT INSIDE[/]" if r.fopt_inside else "[bold red]FOPT OUTSIDE[/]")
    if not r.fopt_inside:
        raise typer.Exit(1)


def _print_effects(r) -> None:
    """Several effects (or a generated one): each hidden effect, a right answer, named or not."""
    from hmcore.scenarios.generators import START_TOLERANCE_DAYS  # imported by the judging

    j, doc = r.verdict, r.diagnosis
    for e in r.effects:
        console.print(f"hidden: [bold]{e.candidate.id}[/] = {e.value:.4g} "
                      f"({e.candidate.description}); a right answer: {e.kind}"
                      + (f", or {' or '.join(e.candidate.details['expect_kinds'])}"
                         if e.candidate.details.get("expect_kinds") else "")
                      + (f" at {', '.join(e.candidate.details['expect_wells'])}"
                         if e.candidate.details.get("expect_wells") else "")
                      + (f" from day {e.candidate.details['start_day']:g} (within "
                         f"{START_TOLERANCE_DAYS:g} days)"
                         if e.candidate.details.get("start_day") is not None else "")
                      + (" over cells i {}-{}, j {}-{} (sharing a quarter or more of "
                         "the columns the two boxes cover)".format(
                          *e.parameter.box[:4]) if e.kind == "regional_permeability"
                         and e.parameter.box else "")
                      + f" - {'[green]named[/]' if j['named'][e.candidate.id] else '[red]not named[/]'}")
    console.print(f"accepted: {', '.join(j['accepted']) or 'none'}; first cause: "
                  f"{doc['causes'][0]['id']}")
    g = doc["gain"]
    console.print(f"held-back E {num(g['heldout_before'], 5)} -> {num(g['heldout_after'], 5)}")


def _print_effect(r) -> None:
    """One library effect or none: ranked first, selected, held-back misfit improved."""
    j, doc, effect = r.verdict, r.diagnosis, (r.effects[0] if r.effects else None)
    if effect is None:
        console.print("hidden: nothing (a control)")
    else:
        console.print(f"hidden: [bold]{effect.candidate.id}[/] = {effect.value:.4g} "
                      f"({effect.candidate.description})")
    first = doc["causes"][0]
    console.print(f"ranked first: [bold]{first['id']}[/] - {first['description']}")
    console.print(f"selected: {doc['selected']['id'] if doc['selected'] else 'none'}")
    console.print(f"ranking: {', '.join(j['ranking'])}")
    g = doc["gain"]
    console.print(f"held-back E {num(g['heldout_before'], 5)} -> {num(g['heldout_after'], 5)}"
                  + (f" (the truth itself: {num(j['truth_E_heldout'], 5)})"
                     if j.get("truth_E_heldout") is not None else ""))
    if j.get("heldout_improved") and not j.get("heldout_E_improved"):
        console.print("  the truth scores no better held-back E than the calibrated model: the "
                      "noise decides E there, so the noise-weighted held-back misfit counts "
                      f"(whitened SSR {num(g['ssr_heldout_before'], 0)} -> "
                      f"{num(g['ssr_heldout_after'], 0)})", highlight=False)
    if r.signal:
        console.print(f"signal of the hidden effect: {signal_text(r.signal)}", highlight=False)
    checks = ("ranked_first", "selected", "heldout_improved")
    console.print("  ".join(f"{c}: {'[green]yes[/]' if j[c] else '[red]no[/]'}" for c in checks))


def signal_text(signal: dict) -> str:
    """One line on how strongly a hidden effect shows in the data (see
    :func:`hmcore.scenarios.hidden.effect_signal`)."""
    if "error" in signal:
        return signal["error"]
    text = (f"chi2 {signal['chi2_fit']:.0f} on the fitted history ({signal['n_fit']} points, "
            f"days <= {signal['history_end_days']:g}), {signal['chi2_heldout']:.0f} on the "
            f"held-back ({signal['n_heldout']} points), before the global parameters absorb any")
    if "chi2_fit_after_globals" in signal:
        text += (f"; {signal['chi2_fit_after_globals']:.0f} on the fitted history (held back "
                 f"{signal['chi2_heldout_after_globals']:.0f}) once the global parameters "
                 "absorb what they can")
    if not signal["visible_in_fitted_history"]:
        text += ("; the fitted history hardly shows it, so no diagnosis can be expected to name "
                 "it from there (fit a longer history)")
    return text
