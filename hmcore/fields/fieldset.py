"""A case's field parameters taken together: the checks that need all of them (unique names,
keywords and seeds, sources that exist, no cycle) and the order their priors are drawn in."""

from __future__ import annotations

from hmcore.errors import Problem
from hmcore.fields.spec import CosimulationPrior, FieldSpec, GeostatisticalPrior


def field_set_problems(fields: list[FieldSpec] | tuple[FieldSpec, ...]) -> list[Problem]:
    """What is wrong with a case's fields taken together, every problem at once: names,
    written keywords and seeds unique, a prior's ``from`` naming another field, no cycle, and
    a co-simulation's source having a normal score (a geostatistical or co-simulated field).
    ``where`` is ``field '<name>'``; the caller adds the case file."""
    problems: list[Problem] = []
    by_name: dict[str, FieldSpec] = {}
    for f in fields:
        if f.name in by_name:
            problems.append(Problem(f"field '{f.name}'", "field names must be unique; the name "
                                    "is used twice", "rename one of them"))
        by_name[f.name] = f
    writers: dict[str, str] = {}
    for f in fields:
        for keyword in f.written:
            if keyword in writers and writers[keyword] != f.name:
                problems.append(Problem(f"field '{f.name}'", f"keyword {keyword} is written by "
                                        f"fields '{writers[keyword]}' and '{f.name}'; each "
                                        "keyword may come from one field",
                                        "drop it from one field's keyword or copies"))
            writers.setdefault(keyword, f.name)
    for f in fields:
        src = f.source_field
        if src is None:
            continue
        if src not in by_name:
            problems.append(Problem(f"field '{f.name}'", f"prior.from = {src!r} names no field; "
                                    f"the fields are {sorted(by_name)}", "name another field"))
        elif src == f.name:
            problems.append(Problem(f"field '{f.name}'", "prior.from names the field itself",
                                    "draw it from another field"))
        elif isinstance(f.prior, CosimulationPrior) and not isinstance(
                by_name[src].prior, (GeostatisticalPrior, CosimulationPrior)):
            problems.append(Problem(f"field '{f.name}'", f"a co-simulation needs a source with "
                                    f"a normal score (a geostatistical or co-simulated field); "
                                    f"'{src}' has prior.source = "
                                    f"{by_name[src].prior.source!r}",
                                    "use source = \"relation\" for it, or co-simulate from a "
                                    "geostatistical field"))
    seeds: dict[int, str] = {}
    for f in fields:
        seed = getattr(f.prior, "seed", None)
        if seed is not None and seeds.setdefault(seed, f.name) != f.name:
            problems.append(Problem(f"field '{f.name}'", f"prior.seed = {seed} is also field "
                                    f"'{seeds[seed]}''s; equal seeds draw the same random "
                                    "numbers, so the two fields would not be independent",
                                    "give every drawn field its own seed"))
    if not problems:
        try:
            draw_order(fields)
        except ValueError as exc:
            problems.append(Problem("fields", str(exc), "break the cycle of prior.from"))
    return problems


def draw_order(fields: list[FieldSpec] | tuple[FieldSpec, ...]) -> list[FieldSpec]:
    """The fields ordered so that every source comes before the fields drawn from it (in the
    case's order otherwise); ValueError naming a cycle."""
    by_name = {f.name: f for f in fields}
    done: list[FieldSpec] = []
    seen: set[str] = set()

    def visit(f: FieldSpec, path: tuple[str, ...]) -> None:
        if f.name in seen:
            return
        if f.name in path:
            cycle = " -> ".join([*path[path.index(f.name):], f.name])
            raise ValueError(f"the fields' priors are drawn from each other in a cycle: {cycle}")
        src = f.source_field
        if src is not None and src in by_name:
            visit(by_name[src], (*path, f.name))
        seen.add(f.name)
        done.append(f)

    for f in fields:
        visit(f, ())
    return done
