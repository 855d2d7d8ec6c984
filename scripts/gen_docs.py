"""Generate the docs pages that come from the code and the benchmark results (no figure typed by hand).

    python scripts/gen_docs.py                      # write docs/reference/*.md and docs/bench/*.md
    python scripts/gen_docs.py --check              # exit 1 naming every page that is out of date
    python scripts/gen_docs.py --results DIR --out DIR   # other inputs / another docs folder (tests)

Pages written (each says what it came from and carries a "do not edit" line):

- ``reference/config.md`` from the config dataclasses, ``reference/cli.md`` from the typer app
  (``scripts/docs_reference.py``);
- ``bench/<name>.md`` for every ``bench/results/<name>.json``: the JSON's own values, rendered generically
  (scalars as key / value tables, lists of records as tables, nested objects as sections), headed by the
  JSON's commit / date / machine fields and the docstring of the bench script that writes it;
- ``bench/index.md``: the list of benchmark pages.

The generated pages are committed, so the site builds from a clone; ``tests/test_docs.py`` regenerates them
into a temporary folder and fails when a committed page differs.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from docs_reference import GENERATED, cli_page, config_page, md_code, md_text  # noqa: E402

PROVENANCE_KEYS = ("commit", "date", "machine", "device", "host", "script", "benchmark")
MAX_TABLE_COLUMNS = 14  # wider record lists are shown transposed (a column per record) ...
MAX_TRANSPOSED = 8  # ... up to this many records; longer ones record by record


# ------------------------------------------------------------------------------------------ values

def _scalar(v: Any) -> bool:
    return v is None or isinstance(v, bool | int | float | str)


def _flat(v: Any) -> bool:
    """A value shown in one table cell: a scalar or a short list of scalars."""
    return _scalar(v) or (isinstance(v, list) and len(v) <= 12 and all(_scalar(x) for x in v))


def cell(v: Any) -> str:
    """A JSON value as its JSON text (floats exactly as stored), table-safe."""
    if isinstance(v, str):
        return md_text(v) if v else "(empty)"
    text = json.dumps(v, ensure_ascii=False)
    return md_code(text) if isinstance(v, list | dict) else md_text(text)


def _records(v: Any) -> bool:
    """A list of objects whose values are flat: one table, a row per object."""
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) and all(_flat(y) for y in x.values())
                                                   for x in v)


def _columns(rows: list[dict]) -> list[str]:
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    return cols


def _heading(level: int, title: str) -> str:
    """A heading down to level 6; deeper levels as a bold line (Markdown has six)."""
    return f"{'#' * level} {title}" if level <= 6 else f"**{title}**"


def render(value: Any, level: int, path: str, out: list[str]) -> None:
    """Append the Markdown of one JSON value; ``path`` names it (``results → kitti``) in headings."""
    if isinstance(value, dict):
        flat = {k: v for k, v in value.items() if _flat(v)}
        if flat:
            out += ["| key | value |", "|---|---|"]
            out += [f"| {md_text(str(k))} | {cell(v)} |" for k, v in flat.items()]
            out.append("")
        for k, v in value.items():
            if k in flat:
                continue
            sub = f"{path} → {k}" if path else str(k)
            out += [_heading(level, md_text(sub)), ""]
            render(v, level + 1, sub, out)
    elif _records(value) and len(_columns(value)) <= MAX_TABLE_COLUMNS:
        cols = _columns(value)
        out += ["| " + " | ".join(md_text(str(c)) for c in cols) + " |", "|" + "---|" * len(cols)]
        out += ["| " + " | ".join(cell(r[c]) if c in r else "" for c in cols) + " |" for r in value]
        out.append("")
    elif _records(value) and len(value) <= MAX_TRANSPOSED:  # wide records side by side: a row per key
        cols = _columns(value)
        out += ["| key | " + " | ".join(f"[{i}]" for i in range(len(value))) + " |", "|---|" + "---|" * len(value)]
        out += [f"| {md_text(str(c))} | " + " | ".join(cell(r[c]) if c in r else "" for r in value) + " |"
                for c in cols]
        out.append("")
    elif isinstance(value, list) and not all(_scalar(x) for x in value):
        for i, item in enumerate(value):
            sub = f"{path} [{i}]"
            out += [_heading(level, md_text(sub)), ""]
            render(item, level + 1, sub, out)
    else:
        out += [cell(value), ""]


# ------------------------------------------------------------------------------------------ pages

def _script_for(name: str) -> tuple[str | None, str]:
    """The bench script that writes ``<name>.json`` and the first paragraph of its docstring."""
    stem = name.split("-")[0]
    candidates = [f"bench/{name.replace('-', '_')}.py", f"bench/{stem}_bench.py", f"bench/{stem}.py",
                  "bench/cuda_check.py" if stem == "cuda_pipeline" else ""]
    for rel in filter(None, candidates):
        path = ROOT / rel
        if path.exists():
            doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
            return rel, " ".join(doc.split("\n\n")[0].split())
    return None, ""


def _provenance(data: Any) -> list[tuple[str, Any]]:
    """The commit / date / machine fields the JSON holds (top level, else in its first level of objects)."""
    found: list[tuple[str, Any]] = []
    if not isinstance(data, dict):
        return found
    for key in PROVENANCE_KEYS:
        if key in data and _flat(data[key]) or key in data and isinstance(data[key], dict):
            found.append((key, data[key]))
    if not any(k in ("commit", "date") for k, _ in found):
        for top, v in data.items():
            if isinstance(v, dict):
                found += [(f"{top} → {k}", v[k]) for k in ("commit", "date") if k in v and _flat(v[k])]
    return found


def bench_page(name: str, data: Any) -> str:
    """The Markdown page of ``bench/results/<name>.json``."""
    script, doc = _script_for(name)
    out = [f"# Benchmark: {name}", "",
           f"*{GENERATED.format(source=f'bench/results/{name}.json')}.*", ""]
    if script:
        out += [f"Written by `{script}`: {md_text(doc)}" if doc else f"Written by `{script}`.", ""]
    else:
        out += ["No bench script writes this file; it was recorded by hand beside a run (see its fields).", ""]
    prov = _provenance(data)
    out += ["| provenance | as the JSON states it |", "|---|---|"]
    out += [f"| {md_text(k)} | {cell(v) if _flat(v) else md_code(json.dumps(v, ensure_ascii=False))} |"
            for k, v in prov] or ["| commit, date | not recorded in this file |"]
    out += ["", "Every figure below is a value of the JSON file, in its order; "
            "the measurement log's prose around them is in [History](../history/index.md).", ""]
    out += ["## Results", ""]
    render(data, 3, "", out)
    while out and out[-1] == "":
        out.pop()
    return "\n".join(out) + "\n"


def bench_index(names: list[str], data: dict[str, Any]) -> str:
    out = ["# Benchmarks", "", f"*{GENERATED.format(source='bench/results/*.json')}.*", "",
           "One page per results file; every figure on them is read from the JSON. Reproduce with "
           "`make bench` or the bench script named on each page. The machine is a shared 2-core CPU unless a page "
           "says otherwise, so seconds from different days are not comparable (ratios measured in one sitting are).",
           "", "| page | written by | commit | date |", "|---|---|---|---|"]
    for name in names:
        script, _ = _script_for(name)
        prov = dict(_provenance(data[name]))
        commit = next((v for k, v in prov.items() if k.endswith("commit")), None)
        date = next((v for k, v in prov.items() if k.endswith("date")), None)
        out.append(f"| [{name}]({name}.md) | {md_code(script) if script else '—'} | "
                   f"{cell(commit) if commit is not None else '—'} | {cell(date) if date is not None else '—'} |")
    return "\n".join(out) + "\n"


def generate(results: Path, reference: bool = True) -> dict[str, str]:
    """``{relative page path: Markdown}`` of every generated page."""
    names = sorted(p.stem for p in results.glob("*.json"))
    data = {n: json.loads((results / f"{n}.json").read_text(encoding="utf-8")) for n in names}
    pages = {f"bench/{n}.md": bench_page(n, data[n]) for n in names}
    pages["bench/index.md"] = bench_index(names, data)
    if reference:
        pages["reference/config.md"] = config_page()
        pages["reference/cli.md"] = cli_page()
    return pages


def write(pages: dict[str, str], out: Path) -> None:
    """Write the pages under ``out`` (each to a temporary name, then renamed: no half-written page)."""
    for rel, text in pages.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".md.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)


def stale(pages: dict[str, str], docs: Path) -> list[str]:
    """The pages whose committed text under ``docs`` differs from ``pages`` (or is missing)."""
    bad = [rel for rel, text in pages.items()
           if not (docs / rel).exists() or (docs / rel).read_text(encoding="utf-8") != text]
    # a page left behind by a results file that is gone
    return bad + sorted(f"bench/{p.name}" for p in (docs / "bench").glob("*.md") if f"bench/{p.name}" not in pages)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--check", action="store_true", help="compare with the pages under --out; write nothing")
    args = ap.parse_args(argv)
    pages = generate(args.results)
    if args.check:
        bad = stale(pages, args.out)
        for rel in bad:
            print(f"out of date: {args.out / rel} (run python scripts/gen_docs.py)")
        return 1 if bad else 0
    write(pages, args.out)
    print(f"wrote {len(pages)} pages under {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
