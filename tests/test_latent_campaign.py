"""A campaign on a ``[latent]`` case end to end with the real simulator and real Prefect
(issue 42): the small synthetic case's PORO and PERMX fields moved by lm through the leading
modes of their 12-member prior. Every call runs the fields its coefficients make; the
reference "as given" runs the basis's image of the deck; a rerun simulates nothing; and
the case errors around ``[latent]`` are stated before any run."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from flows.inputs import scalar_problems
from hmcore.calibration.objective import Objective
from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.fields.grdecl import read_grdecl
from hmcore.fields.grid import read_grid
from hmcore.fields.latent import LatentBasis
from hmcore.fields.members import INCLUDE_NAME
from hmcore.fields.transform import to_physical
from hmcore.model.latent_case import deck_coefficients, latent_basis, latent_case
from hmcore.scenarios.synthetic_fields import FIELDS
from storage import ArtifactStore, EvaluationJournal
from storage.latent import BASIS_DOC, BASIS_FILE, LATENT_STEP

pytestmark = [pytest.mark.opm]
BUDGET = 12


def latent_case_file(folder: Path, small_case: Path, latent: str = "share = 0.8\n") -> Path:
    shutil.copytree(small_case.parent, folder, ignore=shutil.ignore_patterns("truth*"))
    case = folder / small_case.name
    case.write_text(case.read_text() + f"{FIELDS}\n[ensemble]\nsize = 12\n\n[latent]\n{latent}")
    return case


@pytest.fixture(scope="module")
def run(tmp_path_factory, small_case):
    from flows.campaign import campaign_flow

    tmp = tmp_path_factory.mktemp("latent")
    case = latent_case_file(tmp / "case", small_case)
    storage = tmp / "store"
    result = campaign_flow(case=str(case), agent="lm", budget=BUDGET, workers=2,
                           storage=str(storage), campaign="lat")
    return {"case": case, "store": ArtifactStore(storage), "storage": storage,
            "result": result}


def stored_basis(store: ArtifactStore) -> tuple[LatentBasis, dict]:
    version = store.latest("lat", LATENT_STEP)
    doc = version.read_json(BASIS_DOC)
    return LatentBasis.from_table(version.read_parquet(BASIS_FILE), doc["share"],
                                  doc["available"]), doc


def test_the_campaign_moves_the_modes_of_the_cases_prior(run):
    assert isinstance(run["result"], dict), run["result"]
    basis, doc = stored_basis(run["store"])
    loaded = load_case(run["case"])
    again = latent_basis(loaded, read_grid(loaded.deck))  # the same prior as hmflow ensemble's
    np.testing.assert_allclose(basis.modes, again.modes, rtol=1e-9, atol=1e-12)
    assert doc["share"] >= 0.8 and doc["modes"] == basis.k < 12
    records = EvaluationJournal(run["store"], "lat").rows()
    assert len(records) == BUDGET
    assert all(set(r["params"]) == set(basis.names) for r in records)
    case_doc = run["store"].latest("lat", "case").read_json("case.json")
    assert [p["name"] for p in case_doc["parameters"]] == list(basis.names)
    assert {p["kind"] for p in case_doc["parameters"]} == {"latent"}


def test_every_call_runs_the_fields_its_coefficients_make(run):
    basis, _ = stored_basis(run["store"])
    loaded = load_case(run["case"])
    grid = read_grid(loaded.deck)
    poro, permx = loaded.fields
    for r in EvaluationJournal(run["store"], "lat").rows()[-3:]:
        z = [r["params"][n] for n in basis.names]
        x = basis.fields(z)
        written = read_grdecl(Path(r["run_dir"]) / INCLUDE_NAME)
        np.testing.assert_allclose(written["PORO"][grid.active],
                                   to_physical(x[:grid.n_active], poro), rtol=2e-6)
        np.testing.assert_allclose(written["PERMY"][grid.active],
                                   to_physical(x[grid.n_active:], permx), rtol=2e-6)


def test_the_best_case_archive_holds_its_fields_beside_its_deck(run):
    best = run["store"].latest("lat", "best")
    assert INCLUDE_NAME in best.files
    deck = next(f for f in best.files if f.endswith(".DATA"))
    text = best.file(deck).read_text()
    assert f"'{INCLUDE_NAME}'" in text and "/runs/" not in text  # not the run dir's


def test_the_reference_as_given_runs_the_bases_image_of_the_deck(run):
    basis, doc = stored_basis(run["store"])
    loaded = load_case(run["case"])
    floor = EvaluationJournal(run["store"], "lat-reference").get(0)
    z = [floor["params"][n] for n in basis.names]
    np.testing.assert_allclose(z, doc["deck_coefficients"])
    np.testing.assert_allclose(z, deck_coefficients(loaded, read_grid(loaded.deck), basis))
    centre = EvaluationJournal(run["store"], "lat-reference").get(1)
    assert all(v == 0.0 for v in centre["params"].values())


def test_the_prior_joins_the_likelihood_the_best_call_is_chosen_by(run):
    basis, _ = stored_basis(run["store"])
    loaded = latent_case(load_case(run["case"]), basis)
    objective = Objective.of_case(loaded)
    assert objective.prior == basis.names
    best = run["store"].latest("lat", "report").read_json("report.json")["best"]
    record = EvaluationJournal(run["store"], "lat").get(best["index"])
    plain = Objective(objective.name, objective.observations)
    z = np.array([record["params"][n] for n in basis.names])
    n = objective.observations.n_noise("fit")
    assert objective.likelihood(record) == pytest.approx(plain.likelihood(record) + z @ z / n)
    assert best["likelihood"] == pytest.approx(objective.likelihood(record), rel=1e-6)


def test_a_rerun_simulates_nothing(run):
    from flows.campaign import campaign_flow

    runs = sorted(p.name for p in (run["storage"] / "lat" / "runs").iterdir())
    again = campaign_flow(case=str(run["case"]), agent="lm", budget=BUDGET, workers=2,
                          storage=str(run["storage"]), campaign="lat")
    assert isinstance(again, dict), again
    assert sorted(p.name for p in (run["storage"] / "lat" / "runs").iterdir()) == runs
    assert len(run["store"].versions("lat", LATENT_STEP)) == 1


def test_latent_mistakes_are_named_before_any_run(tmp_path, small_case):
    case = latent_case_file(tmp_path / "a", small_case)
    text = case.read_text()
    case.write_text(text + '\n[[parameters]]\nname = "z"\nkind = "latent"\nlow = -1.0\n'
                    "high = 1.0\n")
    with pytest.raises(CaseError) as err:
        load_case(case)
    assert "[[parameters]] 'z'" in str(err.value) and "[latent] section" in str(err.value)

    plain = tmp_path / "b"
    shutil.copytree(small_case.parent, plain, ignore=shutil.ignore_patterns("truth*"))
    other = plain / small_case.name
    other.write_text(other.read_text() + "\n[latent]\nshare = 0.9\n")
    with pytest.raises(CaseError, match="key 'latent'.*no field parameter"):
        load_case(other)

    good = load_case(latent_case_file(tmp_path / "c", small_case))
    assert scalar_problems(good, latent=True) == []
    assert "hmflow run" in scalar_problems(good)[0]  # a benchmark or a diagnosis refuses it


def test_a_resume_keeps_its_basis_and_other_latent_settings_are_refused(run, tmp_path,
                                                                          small_case,
                                                                          monkeypatch):
    import tasks.latent as latent_task

    loaded = load_case(run["case"])
    first = run["store"].versions("lat", LATENT_STEP)
    monkeypatch.setattr(latent_task, "code_version", lambda: "a later commit")
    setup = latent_task.prepare_latent.fn(loaded, str(run["storage"]), "lat")
    assert run["store"].versions("lat", LATENT_STEP) == first  # reused, none drawn again
    assert setup.version.version == first[-1].version
    assert latent_task.latent_conflict(str(run["storage"]), "lat", loaded) is None

    other = load_case(latent_case_file(tmp_path / "d", small_case, "share = 0.7\n"))
    said = latent_task.latent_conflict(str(run["storage"]), "lat", other)
    assert said is not None and "section" in said and "another --campaign" in said
    plain = tmp_path / "e"
    shutil.copytree(small_case.parent, plain, ignore=shutil.ignore_patterns("truth*"))
    said = latent_task.latent_conflict(str(run["storage"]), "lat", load_case(plain / small_case.name))
    assert said is not None and "with a [latent] section" in said


def test_a_benchmark_runs_every_method_over_the_same_modes(tmp_path, small_case):
    from flows.bench import bench_flow, bench_names

    case = latent_case_file(tmp_path / "case", small_case)
    storage = tmp_path / "store"
    result = bench_flow(case=str(case), methods=["lm", "random"], seeds=[1], budget=4,
                        workers=2, storage=str(storage), name="lb")
    assert isinstance(result, dict), result
    store = ArtifactStore(storage)
    _, reference, campaigns = bench_names("", ["lm", "random"], [1], "lb")
    hashes = {name: store.latest(name, LATENT_STEP).manifest["files"][BASIS_FILE]["sha256"]
              for name in (reference, *campaigns)}
    assert len(set(hashes.values())) == 1, hashes  # one basis for the floor and every method
    names = [p["name"] for p in store.latest("lb-reference", "case").read_json(
        "case.json")["parameters"]]
    for name in campaigns:
        records = EvaluationJournal(store, name).rows()
        assert len(records) == 4 and all(list(r["params"]) == names for r in records)
    floor = EvaluationJournal(store, "lb-reference").get(0)
    doc = store.latest("lb-reference", LATENT_STEP).read_json(BASIS_DOC)
    np.testing.assert_allclose([floor["params"][n] for n in names], doc["deck_coefficients"])
    summary = Path(result["summary_path"]).read_text()
    assert "lm" in summary and "random" in summary
