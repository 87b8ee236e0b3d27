"""Tests of the versioned artifact store and the evaluation journal (real files in tmp dirs)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from storage import (ArtifactStore, EvaluationJournal, JournalConflictError, canonical_json,
                     code_version, sha256_json, validate_name)
from storage import provenance

CV = "test-code-1"


def write_text(text: str):
    def writer(directory: Path) -> None:
        (directory / "out.txt").write_text(text)
    return writer


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under root (temp dirs included) with its bytes."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()}


# --- put: reuse and new versions ----------------------------------------------------------

def test_put_writes_version_with_manifest(tmp_path):
    store = ArtifactStore(tmp_path)
    v = store.put("camp", "deck", {"b": 2, "a": [1, 2.5]}, write_text("hello"), CV)
    assert (v.campaign, v.step, v.version, v.reused) == ("camp", "deck", 1, False)
    assert v.path == tmp_path / "camp" / "deck" / "v0001"
    manifest = json.loads((v.path / "manifest.json").read_text())
    assert manifest == v.manifest
    assert manifest["inputs"] == {"a": [1, 2.5], "b": 2}
    assert manifest["inputs_hash"] == sha256_json({"a": [1, 2.5], "b": 2})
    assert manifest["code_version"] == CV
    assert manifest["created"].endswith("+00:00")
    assert manifest["files"] == {"out.txt": {
        "sha256": "2cf24dba5fb0a30e26e83b2ac5b9e29e1b161e5c1fa7425e73043362938b9824", "bytes": 5}}
    assert v.verify() == []
    assert v.file("out.txt").read_text() == "hello"


def test_reuse_when_nothing_changed(tmp_path):
    store = ArtifactStore(tmp_path)
    first = store.put("camp", "deck", {"x": 1, "y": {"z": 2}}, write_text("a"), CV)

    def must_not_run(directory: Path) -> None:
        raise AssertionError("writer called although the version could be reused")

    again = store.put("camp", "deck", {"y": {"z": 2}, "x": 1}, must_not_run, CV)
    assert again.reused and again.version == 1 and again == first
    assert [v.version for v in store.versions("camp", "deck")] == [1]


def test_new_version_when_inputs_or_code_change(tmp_path):
    store = ArtifactStore(tmp_path)
    assert store.put("camp", "deck", {"x": 1}, write_text("a"), CV).version == 1
    assert store.put("camp", "deck", {"x": 2}, write_text("b"), CV).version == 2
    changed_code = store.put("camp", "deck", {"x": 2}, write_text("b"), "test-code-2")
    assert changed_code.version == 3 and not changed_code.reused
    # only the latest version is a reuse candidate
    assert store.put("camp", "deck", {"x": 1}, write_text("a"), CV).version == 4
    assert [v.version for v in store.versions("camp", "deck")] == [1, 2, 3, 4]
    assert store.latest("camp", "deck").version == 4
    assert store.get("camp", "deck", 2).manifest["inputs"] == {"x": 2}


def test_reusable_finds_the_version_of_the_same_inputs_and_code_only(tmp_path):
    """The version put() would return without writing, found before the files are made."""
    store = ArtifactStore(tmp_path)
    assert store.reusable("camp", "report", {"x": 1}, CV) is None  # nothing stored yet
    first = store.put("camp", "report", {"x": 1, "y": [2]}, write_text("a"), CV)
    hit = store.reusable("camp", "report", {"y": [2], "x": 1}, CV)
    assert hit == first and hit.reused and hit.file("out.txt").read_text() == "a"
    assert store.reusable("camp", "report", {"x": 2, "y": [2]}, CV) is None  # other inputs
    assert store.reusable("camp", "report", {"x": 1, "y": [2]}, "test-code-2") is None
    assert store.reusable("camp", "other-step", {"x": 1, "y": [2]}, CV) is None
    first.file("out.txt").write_text("b")  # a damaged version is not reused
    assert store.reusable("camp", "report", {"x": 1, "y": [2]}, CV) is None
    with pytest.raises(ValueError, match="reserved"):
        store.reusable("camp", "evaluations", {}, CV)
    with pytest.raises(ValueError, match="non-empty"):
        store.reusable("camp", "report", {}, "")
    assert [v.version for v in store.versions("camp", "report")] == [1]  # it only looks


def test_inputs_hash_handles_numpy_and_nan(tmp_path):
    store = ArtifactStore(tmp_path)
    v = store.put("camp", "s", {"k": np.int64(3), "f": np.float32(0.5), "n": float("nan"),
                                "arr": np.arange(3), "p": Path("a/b")}, write_text("x"), CV)
    assert v.manifest["inputs"] == {"k": 3, "f": 0.5, "n": None, "arr": [0, 1, 2], "p": "a/b"}
    again = store.put("camp", "s", {"k": 3, "f": 0.5, "n": None, "arr": [0, 1, 2], "p": "a/b"},
                      write_text("y"), CV)
    assert again.reused


def test_unserializable_inputs_rejected_before_writing(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(TypeError, match=r"inputs\['s'\]: cannot store set"):
        store.put("camp", "s", {"s": {1, 2}}, write_text("x"), CV)
    with pytest.raises(TypeError, match="dict keys must be strings"):
        store.put("camp", "s", {"d": {1: "a"}}, write_text("x"), CV)
    assert store.latest("camp", "s") is None


def test_lookup_api(tmp_path):
    store = ArtifactStore(tmp_path)
    assert store.campaigns() == [] and store.latest("c", "s") is None
    assert store.versions("c", "s") == []
    store.put("c2", "report", {}, write_text("r"), CV)
    store.put("c1", "deck", {}, write_text("d"), CV)
    store.put("c1", "best", {}, write_text("b"), CV)
    EvaluationJournal(store, "c1").record(0, {"loss": 1.0})
    assert store.campaigns() == ["c1", "c2"]
    assert store.steps("c1") == ["best", "deck"]  # the journal is not a step
    with pytest.raises(LookupError, match="no version 7 of c1/deck"):
        store.get("c1", "deck", 7)
    with pytest.raises(FileNotFoundError, match="'nope.txt' is not a file"):
        store.latest("c1", "deck").file("nope.txt")


# --- integrity ----------------------------------------------------------------------------

def test_corrupted_file_detected_and_not_reused(tmp_path):
    store = ArtifactStore(tmp_path)
    v1 = store.put("camp", "deck", {"x": 1}, write_text("original"), CV)
    v1.file("out.txt").write_text("tampered")
    problems = v1.verify()
    assert len(problems) == 1 and problems[0].startswith("hash mismatch: out.txt")

    v2 = store.put("camp", "deck", {"x": 1}, write_text("original"), CV)
    assert (v2.version, v2.reused) == (2, False) and v2.verify() == []
    assert v1.file("out.txt").read_text() == "tampered"  # old version left as it is


def test_verify_reports_missing_extra_and_bad_manifest(tmp_path):
    store = ArtifactStore(tmp_path)
    v = store.put("camp", "s", {}, lambda d: [(d / n).write_text(n) for n in ("a", "b")], CV)
    (v.path / "a").unlink()
    (v.path / "extra").write_text("?")
    assert v.verify() == ["missing file: a", "file not in manifest: extra"]
    (v.path / "manifest.json").write_text("{not json")
    broken = store.get("camp", "s", 1)
    assert broken.manifest == {} and "manifest missing, unreadable" in broken.verify()[0]
    assert store.put("camp", "s", {}, write_text("x"), CV).version == 2


def test_same_size_corruption_detected(tmp_path):
    store = ArtifactStore(tmp_path)
    v = store.put("camp", "s", {}, write_text("abc"), CV)
    v.file("out.txt").write_text("abd")
    assert v.verify()[0].startswith("hash mismatch: out.txt")


# --- failures and immutability ------------------------------------------------------------

def test_failing_writer_leaves_nothing(tmp_path):
    store = ArtifactStore(tmp_path)

    def failing(directory: Path) -> None:
        (directory / "partial.parquet").write_bytes(b"half")
        raise RuntimeError("simulator died")

    with pytest.raises(RuntimeError, match="simulator died"):
        store.put("camp", "deck", {}, failing, CV)
    assert store.latest("camp", "deck") is None and store.steps("camp") == []
    assert list((tmp_path / "camp" / "deck").iterdir()) == []
    # and the next put starts at v0001
    assert store.put("camp", "deck", {}, write_text("ok"), CV).version == 1


def test_writer_may_not_write_manifest_or_links(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(ValueError, match="manifest.json, which is reserved"):
        store.put("camp", "s", {}, lambda d: (d / "manifest.json").write_text("{}"), CV)
    with pytest.raises(ValueError, match="not links"):
        store.put("camp", "s", {}, lambda d: (d / "link").symlink_to(tmp_path), CV)
    assert store.latest("camp", "s") is None
    assert list((tmp_path / "camp" / "s").iterdir()) == []


def test_no_version_is_ever_overwritten(tmp_path):
    store = ArtifactStore(tmp_path)
    v1 = store.put("camp", "s", {"i": 0}, write_text("zero"), CV)
    before = snapshot(v1.path)
    for i in range(1, 6):
        store.put("camp", "s", {"i": i}, write_text(str(i)), CV)
    store.put("camp", "s", {"i": 0}, write_text("zero again"), CV)
    assert snapshot(v1.path) == before
    assert [v.version for v in store.versions("camp", "s")] == list(range(1, 8))
    assert all(v.verify() == [] for v in store.versions("camp", "s"))


def test_version_number_taken_concurrently_is_skipped(tmp_path, monkeypatch):
    """Another writer publishes v0001 between our choice of number and our rename."""
    store = ArtifactStore(tmp_path)
    real_rename = os.rename
    state = {"raced": False}

    def racing_rename(src, dst):
        if not state["raced"] and Path(dst).name == "v0001" and Path(src).name.startswith(".tmp-"):
            state["raced"] = True
            store.put("camp", "s", {"who": "other"}, write_text("other"), CV)  # takes v0001
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", racing_rename)
    mine = store.put("camp", "s", {"who": "me"}, write_text("mine"), CV)
    assert state["raced"] and mine.version == 2
    assert mine.manifest["version"] == 2 and mine.verify() == []
    other = store.get("camp", "s", 1)
    assert other.manifest["inputs"] == {"who": "other"} and other.verify() == []
    assert other.file("out.txt").read_text() == "other"


def test_concurrent_puts_from_two_threads(tmp_path):
    store = ArtifactStore(tmp_path)
    barrier = threading.Barrier(2)
    results, errors = [], []

    def worker(n: int) -> None:
        def writer(directory: Path) -> None:
            barrier.wait(timeout=10)  # both temp dirs exist before either publishes
            (directory / "out.txt").write_text(f"writer {n}")
            pd.DataFrame({"n": [n] * 100}).to_parquet(directory / "t.parquet")
        try:
            results.append(store.put("camp", "s", {"same": True}, writer, CV))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(n,)) for n in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert sorted(v.version for v in results) == [1, 2]
    for v in store.versions("camp", "s"):
        assert v.verify() == []
        n = int(v.file("out.txt").read_text().split()[1])
        assert v.read_parquet("t.parquet")["n"].tolist() == [n] * 100
    assert not [p for p in (tmp_path / "camp" / "s").iterdir() if p.name.startswith(".tmp")]


def test_many_threads_distinct_or_reused(tmp_path):
    store = ArtifactStore(tmp_path)
    results = []

    def worker(n: int) -> None:
        results.append(store.put("camp", "s", {"k": n % 2}, write_text(str(n % 2)), CV))

    threads = [threading.Thread(target=worker, args=(n,)) for n in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    published = [v.version for v in results if not v.reused]
    assert len(published) == len(set(published))  # no number handed out twice
    versions = store.versions("camp", "s")
    assert sorted(published) == [v.version for v in versions]
    assert all(v.verify() == [] for v in versions)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.sampled_from([{"a": 1}, {"a": 2}, {"a": 1, "b": [1.5]}]), min_size=1,
                max_size=8))
def test_put_sequence_invariants(sequence):
    with tempfile.TemporaryDirectory() as tmp:
        store = ArtifactStore(tmp)
        seen: dict[int, dict[str, bytes]] = {}
        last_inputs = None
        for i, inputs in enumerate(sequence):
            v = store.put("camp", "s", inputs, write_text(f"{i}"), CV)
            assert v.reused == (inputs == last_inputs)
            if not v.reused:
                assert v.version == len(seen) + 1
                seen[v.version] = snapshot(v.path)
            last_inputs = inputs
            for number, files in seen.items():  # earlier versions unchanged
                assert snapshot(store.get("camp", "s", number).path) == files


# --- put_files and Parquet ----------------------------------------------------------------

def test_parquet_round_trip(tmp_path):
    store = ArtifactStore(tmp_path)
    frame = pd.DataFrame({
        "well": ["P1", "P2", "I1"],
        "time": pd.to_datetime(["2020-01-01", "2020-02-01", "2020-03-01"]),
        "oil": [1.5, np.nan, 3.25],
        "n": np.array([1, 2, 3], dtype="int64"),
        "ok": [True, False, True],
    }, index=pd.Index([10, 20, 30], name="step"))
    v = store.put_files("camp", "eval", {"i": 1}, {"tables/summary.parquet": frame}, CV)
    assert v.files == ["tables/summary.parquet"]
    pd.testing.assert_frame_equal(v.read_parquet("tables/summary.parquet"), frame)


def test_put_files_kinds(tmp_path):
    store = ArtifactStore(tmp_path)
    v = store.put_files("camp", "report", {}, {
        "raw.bin": b"\x00\x01",
        "report.md": "# Résumé\n",
        "summary.json": {"best": np.float64(0.5), "nan": float("nan"), "ids": (1, 2)},
    }, CV)
    assert v.file("raw.bin").read_bytes() == b"\x00\x01"
    assert v.file("report.md").read_text(encoding="utf-8") == "# Résumé\n"
    assert v.read_json("summary.json") == {"best": 0.5, "nan": None, "ids": [1, 2]}
    assert v.verify() == []


@pytest.mark.parametrize("name", ["../escape", "/abs", "a/../b", "", "a//b", "./a", "a\\b",
                                  "manifest.json"])
def test_put_files_rejects_bad_names(tmp_path, name):
    store = ArtifactStore(tmp_path)
    with pytest.raises(ValueError):
        store.put_files("camp", "s", {}, {name: b"x"}, CV)
    assert not (tmp_path / "escape").exists() and store.latest("camp", "s") is None


def test_put_files_rejects_unknown_content(tmp_path):
    with pytest.raises(TypeError, match="content must be bytes, str, DataFrame or dict"):
        ArtifactStore(tmp_path).put_files("camp", "s", {}, {"x": 3.0}, CV)


# --- names --------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", ["", ".", "..", ".hidden", "a/b", "a b", "caf\u00e9", "a\n",
                                 "x" * 129, None, 3])
def test_invalid_names_rejected(tmp_path, bad):
    store = ArtifactStore(tmp_path)
    with pytest.raises(ValueError, match=r"invalid campaign name .*letters, digits"):
        store.put(bad, "s", {}, write_text("x"), CV)
    with pytest.raises(ValueError, match=r"invalid step name .*letters, digits"):
        store.latest("camp", bad)
    with pytest.raises(ValueError, match="invalid campaign name"):
        EvaluationJournal(store, bad)
    assert list(tmp_path.iterdir()) == []


def test_reserved_step_name(tmp_path):
    with pytest.raises(ValueError, match="reserved for the evaluation journal"):
        ArtifactStore(tmp_path).put("camp", "evaluations", {}, write_text("x"), CV)


@given(st.from_regex(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,40}", fullmatch=True))
def test_valid_names_accepted(name):
    assert validate_name("step", name) == name


@given(st.text(min_size=1, max_size=20).filter(
    lambda s: any(not (c.isascii() and (c.isalnum() or c in "-_.")) for c in s)))
def test_names_with_other_characters_rejected(name):
    with pytest.raises(ValueError, match="must be 1-128 characters"):
        validate_name("campaign", name)


# --- canonical JSON -----------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                 max_size=3),
    max_leaves=10)


@given(st.dictionaries(st.text(max_size=5), json_values, max_size=5), st.randoms())
def test_inputs_hash_ignores_key_order(inputs, rnd):
    items = list(inputs.items())
    rnd.shuffle(items)
    assert sha256_json(dict(items)) == sha256_json(inputs)
    assert json.loads(canonical_json(inputs)) == inputs


# --- evaluation journal -------------------------------------------------------------------

def test_journal_record_and_round_trip_with_nan(tmp_path):
    journal = EvaluationJournal(ArtifactStore(tmp_path), "camp")
    assert journal.rows() == [] and list(journal.to_frame().columns) == ["index"]
    p2 = journal.record(2, {"loss": float("nan"), "params": {"permx": np.float32(1.5)},
                            "losses": {"WOPR:P1": 0.25, "WWCT:P1": float("inf")},
                            "status": "ok", "trace": [1, 2]})
    journal.record(np.int64(0), {"loss": np.float64(0.75), "params": {"permx": 1.0},
                                 "losses": {"WOPR:P1": 0.5, "WWCT:P1": 1.0},
                                 "status": "ok", "trace": []})
    assert p2 == tmp_path / "camp" / "evaluations" / "000002.json"
    assert json.loads(p2.read_text())["loss"] is None  # NaN stored as null
    assert [r["index"] for r in journal.rows()] == [0, 2] == journal.indices()
    assert journal.rows()[1]["losses"] == {"WOPR:P1": 0.25, "WWCT:P1": None}

    frame = journal.to_frame()
    assert list(frame.columns[:1]) == ["index"] and frame["index"].tolist() == [0, 2]
    assert frame["loss"].dtype == float and math.isnan(frame["loss"][1])
    assert frame["loss"][0] == 0.75 and frame["params"][1] == {"permx": 1.5}
    flat = journal.to_frame(flatten=True)
    assert flat["params.permx"].tolist() == [1.0, 1.5]
    assert flat["losses.WWCT:P1"][0] == 1.0 and math.isnan(flat["losses.WWCT:P1"][1])
    assert not [p for p in journal.directory.iterdir() if p.name.startswith(".tmp")]


def test_journal_same_content_is_noop_and_conflict_raises(tmp_path):
    journal = EvaluationJournal(ArtifactStore(tmp_path), "camp")
    path = journal.record(5, {"loss": 1.0, "params": {"a": 2}})
    mtime = path.stat().st_mtime_ns
    assert journal.record(5, {"params": {"a": np.int64(2)}, "loss": np.float64(1.0)}) == path
    assert path.stat().st_mtime_ns == mtime
    with pytest.raises(JournalConflictError, match=r"evaluation 5 .*differs in \['loss'\]"):
        journal.record(5, {"loss": 2.0, "params": {"a": 2}})
    with pytest.raises(JournalConflictError, match=r"differs in \['extra'\]"):
        journal.record(5, {"loss": 1.0, "params": {"a": 2}, "extra": None})
    with pytest.raises(JournalConflictError):  # True is not 1
        journal.record(5, {"loss": 1.0, "params": {"a": True}})
    assert json.loads(path.read_text()) == {"index": 5, "loss": 1.0, "params": {"a": 2}}


def test_journal_rejects_bad_index_and_rows(tmp_path):
    journal = EvaluationJournal(ArtifactStore(tmp_path), "camp")
    for bad in (-1, 1.0, True, "3"):
        with pytest.raises(ValueError, match="index must be an integer >= 0"):
            journal.record(bad, {})
    with pytest.raises(ValueError, match="row's own 'index' is 4"):
        journal.record(3, {"index": 4})
    with pytest.raises(TypeError, match="cannot store object"):
        journal.record(3, {"x": object()})
    assert journal.rows() == []


def test_journal_failed_write_leaves_no_record(tmp_path, monkeypatch):
    journal = EvaluationJournal(ArtifactStore(tmp_path), "camp")

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        journal.record(1, {"loss": 1.0})
    assert list(journal.directory.iterdir()) == []


def test_a_record_being_written_is_not_a_json_file_to_a_reader(tmp_path, monkeypatch):
    """A reader that lists ``*.json`` while the writer is between write and rename (a kill -9,
    a test polling a live campaign) sees records only, never the temporary file (CI of
    b942589 failed on ``int('.tmp-…')``)."""
    journal = EvaluationJournal(ArtifactStore(tmp_path), "camp")
    seen = []

    def replace_after_looking(src, dst):
        seen.append((Path(src).name, sorted(p.name for p in journal.directory.glob("*.json"))))
        return real_replace(src, dst)

    real_replace = os.replace
    monkeypatch.setattr(os, "replace", replace_after_looking)
    journal.record(1, {"loss": 1.0})
    assert seen[0][0].startswith(".tmp-") and seen[0][1] == []
    assert [p.name for p in journal.directory.glob("*.json")] == [journal.path(1).name]


journal_rows = st.dictionaries(
    st.text(max_size=6).filter(lambda k: k != "index"),
    st.floats() | st.integers(-10**6, 10**6) | st.text(max_size=5) | st.none()
    | st.dictionaries(st.text(max_size=4), st.floats(), max_size=3)
    | st.lists(st.floats(allow_nan=False), max_size=3),
    max_size=5)


def _nan_to_none(value):
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    return value


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.integers(0, 10**7), journal_rows, max_size=6))
def test_journal_round_trip(records):
    with tempfile.TemporaryDirectory() as tmp:
        journal = EvaluationJournal(ArtifactStore(tmp), "camp")
        for index, row in records.items():
            journal.record(index, row)
            journal.record(index, row)  # idempotent, NaN included
        expected = [{**_nan_to_none(records[i]), "index": i} for i in sorted(records)]
        assert journal.rows() == expected
        assert len(journal.to_frame()) == len(records)


# --- code version -------------------------------------------------------------------------

def test_code_version_string():
    provenance.code_version.cache_clear()
    try:
        value = code_version()
        assert isinstance(value, str) and value
    finally:
        provenance.code_version.cache_clear()


def test_code_version_without_git_or_distribution(monkeypatch):
    def no_git(*args, **kwargs):
        assert kwargs.get("check") is True and kwargs.get("timeout")
        raise subprocess.TimeoutExpired(args[0], kwargs["timeout"])

    def no_dist(name):
        raise provenance.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(provenance.subprocess, "run", no_git)
    provenance.code_version.cache_clear()
    try:
        monkeypatch.setattr(provenance.metadata, "version", lambda name: "9.9.9")
        assert code_version() == "9.9.9+git.unknown"
        provenance.code_version.cache_clear()
        monkeypatch.setattr(provenance.metadata, "version", no_dist)
        assert code_version() == "unknown"
    finally:
        provenance.code_version.cache_clear()


def test_storage_is_a_plain_library():
    code = ("import sys, storage; "
            "bad = [m for m in sys.modules if m.split('.')[0] in "
            "('prefect', 'hmcore', 'tasks', 'flows')]; assert not bad, bad")
    subprocess.run([os.sys.executable, "-c", code], check=True, timeout=60,
                   cwd=Path(__file__).resolve().parents[1])


def test_campaign_resumes_on_a_new_version_of_the_same_case_content(tmp_path):
    """Newer hmflow code writes a new case version of the same content: the campaign resumes;
    other content under the same name is refused."""
    from flows.campaign import check_campaign_settings

    def settings(version: int, content: str) -> dict:
        return {"case_artifact": {"campaign": "c", "step": "case", "version": version,
                                  "content_hash": content}, "agent": "sac", "seed": 0,
                "agent_settings": {}}

    check_campaign_settings(str(tmp_path), "c", settings(1, "aaa"))
    check_campaign_settings(str(tmp_path), "c", settings(2, "aaa"))  # same content: resumes
    with pytest.raises(ValueError, match="bound to a case that is not in the store "
                                         r"\(version 1 of c/case\)"):
        check_campaign_settings(str(tmp_path), "c", settings(3, "bbb"))  # no such version
    with pytest.raises(ValueError, match="other settings"):
        check_campaign_settings(str(tmp_path), "c", {**settings(2, "aaa"), "seed": 1})


def test_a_case_stored_by_older_code_is_the_same_case_and_a_changed_setting_is_named(tmp_path):
    """A campaign started before hmflow stored more settings (a case.json without them, a
    history without the 'controlled' column) resumes on today's version of the same case; a
    case file with a comment added resumes too; a changed physics setting is refused, naming
    the setting and both values."""
    import json

    from flows.campaign import check_campaign_settings
    from hmcore.cases import load_case
    from hmcore.scenarios.synthetic import ensure_synthetic_case
    from storage import ArtifactStore
    from tasks.case import prepare_deck

    shutil.copytree(Path(ensure_synthetic_case()).parent, tmp_path / "syn")
    root, toml = str(tmp_path / "store"), tmp_path / "syn" / "case.toml"
    store = ArtifactStore(root)
    today = prepare_deck.fn(load_case(toml), str(toml), root, "c")

    def older(directory: Path) -> None:  # today's version as older code wrote it
        shutil.copytree(today.path / "deck", directory / "deck")
        shutil.copy(today.path / "case.toml", directory / "case.toml")
        stored = json.loads((today.path / "case.json").read_text())
        del stored["simulator"]["threads"], stored["physics"]["perm_cap_ratio"]
        for p in stored["parameters"]:
            del p["region_numbers"]
        (directory / "case.json").write_text(json.dumps(stored))
        today.read_parquet("observed.parquet").drop(columns="controlled").to_parquet(
            directory / "observed.parquet", index=False)

    old = store.put("c", "case", {"older": True}, older, "older")
    assert old.ref()["content_hash"] != today.ref()["content_hash"]
    settings = {"agent": "sac", "seed": 0}
    check_campaign_settings(root, "c", {"case_artifact": old.ref(), **settings})
    check_campaign_settings(root, "c", {"case_artifact": today.ref(), **settings})  # resumes

    toml.write_text(toml.read_text() + "\n# a comment\n")
    commented = prepare_deck.fn(load_case(toml), str(toml), root, "c")
    assert commented.version > today.version
    check_campaign_settings(root, "c", {"case_artifact": commented.ref(), **settings})

    toml.write_text(toml.read_text() + "\n[physics]\nperm_cap_md = 20000\n")
    capped = prepare_deck.fn(load_case(toml), str(toml), root, "c")
    with pytest.raises(ValueError, match=r"another case: physics.perm_cap_md: None \(stored\), "
                                         r"20000.0 \(given\)\. Set the stored values"):
        check_campaign_settings(root, "c", {"case_artifact": capped.ref(), **settings})


def test_journal_get_returns_one_record_or_none(tmp_path):
    from storage import ArtifactStore, EvaluationJournal

    j = EvaluationJournal(ArtifactStore(tmp_path), "c")
    assert j.get(3) is None
    j.record(3, {"E": 0.5})
    assert j.get(3) == {"E": 0.5, "index": 3} and j.get(4) is None


# --- links: the store never writes through one ----------------------------------------------

@pytest.mark.parametrize("linked", ["campaign", "step", "journal"])
def test_a_linked_folder_is_refused_and_nothing_is_written_through_it(tmp_path, linked):
    from storage import LinkRefusedError

    root, outside = tmp_path / "store", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    link = {"campaign": root / "c", "step": root / "c" / "s",
            "journal": root / "c" / "evaluations"}[linked]
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(outside, target_is_directory=True)
    store = ArtifactStore(root)
    with pytest.raises(LinkRefusedError, match="symbolic link"):
        if linked == "journal":
            EvaluationJournal(store, "c").record(0, {"E": 1.0})
        else:
            store.put("c", "s", {"a": 1}, write_text("x"), CV)
    if linked == "campaign":  # the journal of a linked campaign is refused as well
        with pytest.raises(LinkRefusedError):
            EvaluationJournal(store, "c").record(0, {"E": 1.0})
    assert list(outside.iterdir()) == []  # nothing written outside the root


def test_a_file_where_a_campaign_folder_belongs_is_refused(tmp_path):
    from storage import LinkRefusedError

    (tmp_path / "c").write_text("not a folder")
    with pytest.raises(LinkRefusedError, match="not a folder"):
        ArtifactStore(tmp_path).put("c", "s", {}, write_text("x"), CV)


def test_a_linked_root_is_allowed(tmp_path):
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "root").symlink_to(real, target_is_directory=True)
    version = ArtifactStore(tmp_path / "root").put("c", "s", {}, write_text("x"), CV)
    assert (real / "c" / "s" / "v0001" / "out.txt").read_text() == "x"
    assert version.version == 1


def test_campaign_settings_are_bound_once_through_the_store(tmp_path):
    store = ArtifactStore(tmp_path)
    assert store.settings("c") is None and not store.has_campaign("c")
    store.bind_settings("c", {"agent": "lm", "seed": np.int64(3)})
    assert store.settings("c") == {"agent": "lm", "seed": 3} and store.has_campaign("c")
    store.bind_settings("c", {"seed": 3, "agent": "lm"})  # the same settings: a no-op
    with pytest.raises(ValueError, match="bound to other settings"):
        store.bind_settings("c", {"agent": "cmaes", "seed": 3})
    assert store.settings("c") == {"agent": "lm", "seed": 3}
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["campaign.json"]  # no temp left
    with pytest.raises(ValueError):
        store.bind_settings("../outside", {})
