"""The case fingerprint covers every file the deck reads, wherever it lives: editing an
INCLUDE file outside the deck's folder and resuming is refused with the file named; an
unrelated new file beside the deck does not block the resume (real Prefect flow; a fake
evaluator stands in for nothing: the campaign is refused before any simulation). The deck is
the small synthetic case's (conftest.small_case)."""

from __future__ import annotations

import shutil

import pytest


def _case_with_outside_include(tmp_path, small_case):
    src = small_case.parent
    case_dir, shared = tmp_path / "case", tmp_path / "shared"
    case_dir.mkdir()
    shared.mkdir()
    deck = (src / "SYNTH.DATA").read_text()
    # move the PVTW keyword's record into an include file in another folder
    start = deck.index("\nPVTW\n") + 1
    end = deck.index(" /\n", start) + 2
    (shared / "pvtw.inc").write_text(deck[start:end] + "\n")
    (case_dir / "SYNTH.DATA").write_text(deck[:start] + f"INCLUDE\n '{shared / 'pvtw.inc'}' /\n"
                                         + deck[end:])
    shutil.copy(src / "observed.csv", case_dir / "observed.csv")
    shutil.copy(src / "case.toml", case_dir / "case.toml")
    return case_dir / "case.toml", shared / "pvtw.inc"


def test_deck_files_follow_includes_outside_the_folder_and_ignore_the_rest(tmp_path, small_case):
    from hmcore.cases import load_case
    from hmcore.model.fingerprint import deck_file_hashes

    case_file, inc = _case_with_outside_include(tmp_path, small_case)
    (case_file.parent / "notes.txt").write_text("unrelated")
    files = deck_file_hashes(load_case(case_file))
    assert set(files) == {"SYNTH.DATA", str(inc)}


@pytest.mark.opm
def test_resume_on_a_changed_include_is_refused_with_the_file_named(tmp_path, small_case):
    from flows.campaign import campaign_flow

    case_file, inc = _case_with_outside_include(tmp_path, small_case)
    store = tmp_path / "store"
    first = campaign_flow(case=str(case_file), agent="random", budget=1, workers=1,
                          storage=str(store), campaign="inc", return_state=True)
    assert first.is_completed(), first.message
    (case_file.parent / "notes.txt").write_text("unrelated")  # does not block a resume
    runs = sorted((store / "inc" / "runs").iterdir())
    again = campaign_flow(case=str(case_file), agent="random", budget=1, workers=1,
                          storage=str(store), campaign="inc", return_state=True)
    assert again.is_completed(), again.message  # resumed (its 1 call journaled), not refused
    assert sorted((store / "inc" / "runs").iterdir()) == runs  # nothing simulated again
    inc.write_text(inc.read_text().replace("PVTW", "PVTW\n-- edited", 1))
    refused = campaign_flow(case=str(case_file), agent="random", budget=3, workers=1,
                            storage=str(store), campaign="inc", return_state=True)
    assert refused.is_failed() and f"{inc} changed" in refused.message, refused.message
    assert sorted((store / "inc" / "runs").iterdir()) == runs  # nothing simulated
    # --fork: a new campaign on the changed model, recording where it comes from; the old
    # campaign is left exactly as it was
    import json

    old = {p: p.read_bytes() for p in (store / "inc").rglob("*") if p.is_file()}
    assert "--fork" in refused.message
    forked = campaign_flow(case=str(case_file), agent="random", budget=1, workers=1,
                           storage=str(store), campaign="inc-fork", forked_from="inc",
                           return_state=True)
    assert forked.is_completed(), forked.message
    settings = json.loads((store / "inc-fork" / "campaign.json").read_text())
    before = json.loads((store / "inc" / "campaign.json").read_text())
    assert settings["forked_from"] == {"campaign": "inc", "case_artifact":
                                       before["case_artifact"], "deck_files": before["deck_files"]}
    assert settings["deck_files"][str(inc)] != before["deck_files"][str(inc)]
    assert {p: p.read_bytes() for p in (store / "inc").rglob("*") if p.is_file()} == old
    fork_runs = sorted((store / "inc-fork" / "runs").iterdir())
    again = campaign_flow(case=str(case_file), agent="random", budget=1, workers=1,
                          storage=str(store), campaign="inc-fork", forked_from="inc",
                          return_state=True)  # the same fork resumes, not refused
    assert again.is_completed(), again.message
    assert sorted((store / "inc-fork" / "runs").iterdir()) == fork_runs  # nothing simulated
    assert len(list((store / "inc-fork" / "evaluations").glob("*.json"))) == 1
    assert {p: p.read_bytes() for p in (store / "inc").rglob("*") if p.is_file()} == old
