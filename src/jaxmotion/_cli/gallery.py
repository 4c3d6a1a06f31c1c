"""`python -m jaxmotion gallery`: one self-contained HTML page of results folders.

The page holds, for every results folder (a `run`, a multi-stage run, a `compose`), its
motion (`motion.gif`), its learning plot(s), its check verdict and its key figures, read
from the files the folder holds (nothing is simulated). Images are embedded as data URIs
and the page's style and script are inline, so the one file can be mailed around and
opened anywhere; its Content-Security-Policy forbids every other load.
"""

import base64
import datetime as _dt
import html
import json
import math
import os
import re
import tempfile
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .config import ConfigError

WHAT_A_RESULTS_FOLDER_HOLDS = (
    "a results folder (written by `run`, a multi-stage run or `compose`) holds config.toml "
    "and summary.json, with best_controller.json, history.csv and learning_plot.png (a "
    "multi-stage run: one stage-K-NAME/ subfolder per stage) and motion.gif unless "
    "animation was off; a folder holding results folders (a sweep) is accepted too"
)
PAGE_SUFFIXES = (".html", ".htm")
_IMAGE_TYPES = {b"GIF87a": "image/gif", b"GIF89a": "image/gif", b"\x89PNG\r\n\x1a\n": "image/png"}
_STAMP = re.compile(r"-(\d{4})(\d{2})(\d{2})-(\d{2})(\d{2})(\d{2})(?:-\d+)?$")


@dataclass(frozen=True)
class Verdict:
    """A check's verdict as the page shows it: `state` is "passed", "failed" or "none"."""

    label: str
    state: str
    details: tuple[tuple[str, dict | None], ...] = ()  # (heading, a check's to_dict())


@dataclass(frozen=True)
class Result:
    """What the page shows of one results folder."""

    folder: Path
    kind: str  # "run", "N stages" or "composite"
    name: str
    body: str
    controller: str
    search: str
    best_fitness: float | None
    best_text: str
    evaluations: int | None
    time_s: float | None  # a run's wall time; a composite's search time
    seed: Any
    date: str
    verdict: Verdict
    figures: tuple[tuple[str, str], ...]  # (what, value) as the card lists them
    motion: Path | None
    plots: tuple[tuple[str, Path], ...]  # (caption, PNG)
    missing_plots: tuple[str, ...]


def _is_results_folder(path: Path) -> bool:
    return (path / "config.toml").is_file()


def _natural(path: Path) -> list:
    """A name's sort key with its numbers as numbers: a sweep's seed2 before seed10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def find_results(paths: Sequence[str | Path]) -> list[Path]:
    """The results folders `paths` name: each path a results folder, or a folder holding
    results folders (its direct subfolders with a `config.toml`, by name, numbers in names
    compared as numbers; hidden ones, such as a running search's `.NAME.partial/` or a
    sweep's `.LABEL.task/`, are skipped). A folder named twice is listed
    once.

    **Raises:** `ConfigError` naming a path that is neither (and what a results folder
    holds)."""
    found: list[Path] = []
    seen: set[Path] = set()
    for raw in paths:
        path = Path(raw)
        if not path.is_dir():
            what = "a file" if path.exists() else "no such folder"
            raise ConfigError(
                f"{path}: not a results folder ({what}); {WHAT_A_RESULTS_FOLDER_HOLDS}"
            )
        if _is_results_folder(path):
            folders = [path]
        else:
            folders = sorted(
                (
                    p
                    for p in path.iterdir()
                    if p.is_dir() and not p.name.startswith(".") and _is_results_folder(p)
                ),
                key=_natural,
            )
            if not folders:
                raise ConfigError(
                    f"{path}: not a results folder (no config.toml) and holds none; "
                    f"{WHAT_A_RESULTS_FOLDER_HOLDS}"
                )
        for folder in folders:
            key = folder.resolve()
            if key not in seen:
                seen.add(key)
                found.append(folder)
    return found


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid JSON: {e}") from None


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None


def _number(value: Any) -> float | None:
    """A summary's number (`_json_number` writes non-finite ones as strings)."""
    if isinstance(value, bool) or value is None:
        return None
    if isinstance(value, int | float):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _short(value: Any) -> str:
    x = _number(value)
    if x is None:
        return "—" if value is None else str(value)
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return f"{x:.4g}" if math.isfinite(x) else str(x)


def _table(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _body_label(config: dict[str, Any]) -> str:
    body = _table(config.get("body"))
    if "figure" in body:
        return str(body["figure"])
    return str(body.get("lattice", "cube"))


def _family(folder: Path, table: dict[str, Any]) -> str:
    """A search's controller family: its saved best controller's, else its config's."""
    saved = _table(_read_json(folder / "best_controller.json"))
    family = saved.get("family") or _table(table.get("controller")).get("family")
    return str(family) if family else "?"


def _algorithm(table: dict[str, Any]) -> str:
    search = _table(table.get("search"))
    algorithm = str(search.get("algorithm", "parallel_hill_climb"))
    runs = search.get("runs")
    if isinstance(runs, int) and runs > 1:
        algorithm += f" ({runs} runs)"
    return algorithm


def _unique(items: Sequence[str]) -> str:
    return ", ".join(dict.fromkeys(items)) or "?"


def _verdict(check: Any) -> Verdict:
    if not isinstance(check, dict):
        return Verdict("no check", "none")
    passed = bool(check.get("passed"))
    name = str(check.get("name", "check"))
    return Verdict(
        f"{name}: {'passed' if passed else 'failed'}",
        "passed" if passed else "failed",
        ((name, check),),
    )


def _date(folder: Path) -> str:
    stamp = _STAMP.search(folder.name)
    if stamp is not None:
        y, mo, d, h, mi, _ = stamp.groups()
        return f"{y}-{mo}-{d} {h}:{mi}"
    when = _dt.datetime.fromtimestamp((folder / "summary.json").stat().st_mtime)
    return when.strftime("%Y-%m-%d %H:%M")


def _plots(folder: Path, label: str = "") -> tuple[list[tuple[str, Path]], list[str]]:
    plots, missing = [], []
    for name in ("learning_plot.png", "learning_curves.png"):
        path = folder / name
        if path.is_file():
            plots.append((f"{label}{name}", path))
        elif name == "learning_plot.png":
            missing.append(f"{label}{name}")
    return plots, missing


def read_result(folder: str | Path) -> Result:
    """Read what the page shows of one results folder (its config.toml, summary.json, best
    controller, images).

    **Raises:** `ConfigError` naming the folder or file when it is not a complete results
    folder or a file in it does not parse."""
    folder = Path(folder)
    if not _is_results_folder(folder):
        raise ConfigError(
            f"{folder}: not a results folder (no config.toml); {WHAT_A_RESULTS_FOLDER_HOLDS}"
        )
    config = _read_toml(folder / "config.toml")
    summary = _read_json(folder / "summary.json")
    if not isinstance(summary, dict):
        raise ConfigError(
            f"{folder}: not a complete results folder (no summary.json, or not a table); "
            f"{WHAT_A_RESULTS_FOLDER_HOLDS}"
        )
    motion = folder / "motion.gif"
    common = {
        "folder": folder,
        "name": str(summary.get("name") or config.get("name") or folder.name),
        "evaluations": summary.get("evaluations"),
        "seed": summary.get("seed", config.get("seed")),
        "date": _date(folder),
        "motion": motion if motion.is_file() else None,
    }
    if "phase" in config:
        kind = _composite(folder, config, summary)
    elif "stages" in summary:
        kind = _stages(folder, config, summary)
    else:
        kind = _run(folder, config, summary)
    best = kind.pop("best")
    return Result(
        best_fitness=_number(best),
        best_text=kind.pop("best_text", _short(best)),
        time_s=_number(kind.pop("time")),
        **{k: tuple(v) if isinstance(v, list) else v for k, v in kind.items()},
        **common,
    )


def _run(folder: Path, config: dict, summary: dict) -> dict[str, Any]:
    plots, missing = _plots(folder)
    verdict = _verdict(summary.get("check"))
    runs = summary.get("runs")
    if isinstance(runs, list) and runs:
        passed = sum(1 for r in runs if _table(_table(r).get("check")).get("passed"))
        checked = [r for r in runs if isinstance(_table(r).get("check"), dict)]
        if checked:
            verdict = Verdict(
                f"{verdict.label} ({passed} of {len(runs)} runs pass)",
                verdict.state,
                verdict.details
                + tuple((f"run {_table(r).get('run')}", _table(r).get("check")) for r in checked),
            )
    figures = [
        ("best fitness", _short(summary.get("best_fitness"))),
        *((f"term {k}", _short(v)) for k, v in _table(summary.get("terms")).items()),
        ("evaluations", _short(summary.get("evaluations"))),
        ("non-finite evaluations", _short(summary.get("nonfinite_evaluations"))),
        ("wall time (s)", _short(summary.get("wall_time_s"))),
        ("search time (s)", _short(summary.get("search_time_s"))),
        ("steady evaluations/s", _short(summary.get("steady_evals_per_s"))),
        ("seed", _short(summary.get("seed"))),
        ("duration (s)", _short(_table(config.get("simulation")).get("duration"))),
        ("devices", _short(summary.get("devices"))),
        ("jax", str(summary.get("jax", "—"))),
    ]
    return {
        "kind": "run",
        "body": _body_label(config),
        "controller": _family(folder, config),
        "search": _algorithm(config),
        "best": summary.get("best_fitness"),
        "time": summary.get("wall_time_s"),
        "verdict": verdict,
        "figures": figures,
        "plots": plots,
        "missing_plots": missing,
    }


def _stages(folder: Path, config: dict, summary: dict) -> dict[str, Any]:
    stages = [_table(s) for s in summary.get("stages") or []]
    tables = [_table(t) for t in config.get("stage") or []]
    top = {k: v for k, v in config.items() if k != "stage"}
    families, algorithms, plots, missing, details = [], [], [], [], []
    figures: list[tuple[str, str]] = []
    for i, stage in enumerate(stages):
        table = {**top, **(tables[i] if i < len(tables) else {})}
        sub = folder / str(stage.get("folder", ""))
        label = f"stage {stage.get('stage', i + 1)} {stage.get('name', '')}".rstrip()
        families.append(_family(sub, table))
        algorithms.append(_algorithm(table))
        found, lost = _plots(sub, f"{label}: ")
        plots += found
        missing += lost
        check = stage.get("check")
        verdict = "" if not isinstance(check, dict) else "; " + _verdict(check).label
        figures.append(
            (
                label,
                f"best fitness {_short(stage.get('best_fitness'))}, "
                f"{_short(stage.get('evaluations'))} evaluations, "
                f"{_short(stage.get('wall_time_s'))} s{verdict}",
            )
        )
        if isinstance(check, dict):
            details.append((label, check))
    verdict = _verdict(summary.get("check"))
    verdict = Verdict(
        verdict.label,
        verdict.state,
        verdict.details + tuple(details),
    )
    bests = [_short(s.get("best_fitness")) for s in stages]
    figures += [
        ("evaluations", _short(summary.get("evaluations"))),
        ("duration (s)", _short(summary.get("duration_s"))),
        ("wall time (s)", _short(summary.get("wall_time_s"))),
        ("seed", _short(summary.get("seed"))),
        ("jax", str(summary.get("jax", "—"))),
    ]
    return {
        "kind": f"{len(stages)} stages",
        "body": _body_label(config),
        "controller": _unique(families),
        "search": _unique(algorithms),
        "best": None,  # each stage has its own objective: no single best, each one's shown
        "best_text": " / ".join(bests) or "—",
        "time": summary.get("wall_time_s"),
        "verdict": verdict,
        "figures": figures,
        "plots": plots,
        "missing_plots": missing,
    }


def _composite(folder: Path, config: dict, summary: dict) -> dict[str, Any]:
    best = _table(summary.get("best"))
    checks = _table(best.get("checks"))
    verdicts = {name: _verdict(check) for name, check in checks.items()}
    checked = [v for v in verdicts.values() if v.state != "none"]
    passed = sum(v.state == "passed" for v in checked)
    if checked:
        verdict = Verdict(
            f"{passed} of {len(checked)} phases pass",
            "passed" if passed == len(checked) else "failed",
            tuple((f"phase {name}", checks[name]) for name, v in verdicts.items() if v.details),
        )
    else:
        verdict = Verdict("no check", "none")
    saved = _table(_read_json(folder / "best_controller.json"))
    children = _table(saved.get("params")).get("controllers") or []
    families = _unique([str(_table(c).get("family", "?")) for c in children])
    phases = [_table(p) for p in config.get("phase") or []]
    body = "?"
    for phase in phases:  # the components' body (a compose folder names its components)
        source = phase.get("results")
        if isinstance(source, str) and (Path(source) / "config.toml").is_file():
            try:
                body = _body_label(_read_toml(Path(source) / "config.toml"))
            except ConfigError:
                continue
            break
    plots, missing = _plots(folder)
    equal = _table(summary.get("equally_spaced"))
    figures = [
        ("best fitness", _short(best.get("fitness"))),
        ("equally spaced transitions' fitness", _short(equal.get("fitness"))),
        ("improved on equal spacing", str(summary.get("improved_on_equal_spacing", "—"))),
        ("phases", ", ".join(str(p.get("name", "?")) for p in phases) or "—"),
        ("best transitions (s)", ", ".join(_short(t) for t in best.get("transitions") or [])),
        *((f"script {k}", _short(v)) for k, v in _table(best.get("values")).items()),
        ("evaluations", _short(summary.get("evaluations"))),
        ("search time (s)", _short(summary.get("search_time_s"))),
        ("seed", _short(summary.get("seed"))),
    ]
    return {
        "kind": "composite",
        "body": body,
        "controller": f"sequence of {families}" if children else "sequence",
        "search": "transition search",
        "best": best.get("fitness"),
        "time": summary.get("search_time_s"),
        "verdict": verdict,
        "figures": figures,
        "plots": plots,
        "missing_plots": missing,
    }


def _data_uri(path: Path) -> str | None:
    """The image as a data URI, or None if the file is not a GIF or PNG image."""
    data = path.read_bytes()
    for magic, mime in _IMAGE_TYPES.items():
        if data.startswith(magic):
            return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"
    return None


_STYLE = """
:root { --fg: #1d232a; --muted: #5b6670; --line: #d9dee3; --bg: #f6f7f9; --card: #fff;
  --pass: #1a7f37; --pass-bg: #dcf5e3; --fail: #b42318; --fail-bg: #fde4e1;
  --none: #5b6670; --none-bg: #eceff2; --accent: #2255aa; }
* { box-sizing: border-box; }
body { margin: 0; font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif;
  color: var(--fg); background: var(--bg); }
header, main { max-width: 1280px; margin: 0 auto; padding: 0 20px; }
header { padding-top: 24px; }
h1 { margin: 0 0 4px; font-size: 26px; }
.sub { color: var(--muted); margin: 0 0 16px; }
.controls { display: flex; gap: 12px; align-items: center; margin-bottom: 10px; flex-wrap: wrap; }
#filter { flex: 1 1 320px; padding: 8px 10px; font: inherit; border: 1px solid var(--line);
  border-radius: 6px; }
#shown { color: var(--muted); }
.tablewrap { overflow-x: auto; }
table { width: 100%; border-collapse: collapse; background: var(--card);
  border: 1px solid var(--line); border-radius: 8px; overflow: hidden; }
th, td { padding: 6px 8px; border-bottom: 1px solid var(--line); text-align: left;
  white-space: nowrap; }
td.wrap { white-space: normal; min-width: 8em; }
code { font-family: ui-monospace, monospace; font-size: 13px; overflow-wrap: anywhere; }
th.num, td.num { text-align: right; font-variant-numeric: tabular-nums; }
th button { all: unset; cursor: pointer; font-weight: 600; }
th button::after { content: " \\2195"; color: #aab2ba; }
th[aria-sort=ascending] button::after { content: " \\25B2"; color: var(--accent); }
th[aria-sort=descending] button::after { content: " \\25BC"; color: var(--accent); }
tbody tr:hover { background: #f0f4fb; }
a { color: var(--accent); text-decoration: none; }
a:hover { text-decoration: underline; }
.badge { display: inline-block; white-space: nowrap; padding: 1px 8px; border-radius: 10px;
  font-size: 13px; font-weight: 600; }
.badge.passed { color: var(--pass); background: var(--pass-bg); }
.badge.failed { color: var(--fail); background: var(--fail-bg); }
.badge.none { color: var(--none); background: var(--none-bg); }
#cards { display: grid; gap: 18px; padding-top: 22px; padding-bottom: 40px; }
.card { background: var(--card); border: 1px solid var(--line); border-radius: 10px;
  padding: 16px 18px; }
.card h2 { margin: 0; font-size: 20px; display: flex; gap: 10px; align-items: center;
  flex-wrap: wrap; }
.card .path { color: var(--muted); font-family: ui-monospace, monospace; font-size: 12.5px;
  margin: 4px 0 12px; word-break: break-all; }
.media { display: flex; gap: 14px; flex-wrap: wrap; align-items: flex-start; }
figure { margin: 0; flex: 1 1 360px; max-width: 560px; }
figure img { width: 100%; height: auto; border: 1px solid var(--line); border-radius: 6px;
  background: #fff; }
figcaption { color: var(--muted); font-size: 13px; }
.absent { flex: 1 1 360px; max-width: 560px; min-height: 120px; display: flex;
  align-items: center; justify-content: center; text-align: center; padding: 16px;
  border: 2px dashed var(--line); border-radius: 6px; color: var(--muted); }
dl { display: grid; grid-template-columns: max-content 1fr; gap: 2px 16px; margin: 14px 0 6px; }
dt { color: var(--muted); }
dd { margin: 0; font-variant-numeric: tabular-nums; }
details { margin-top: 8px; }
summary { cursor: pointer; font-weight: 600; }
ul.criteria { margin: 6px 0; padding-left: 20px; }
li.ok::marker { content: "\\2714  "; color: var(--pass); }
li.no::marker { content: "\\2718  "; color: var(--fail); }
.checkfigures { color: var(--muted); font-size: 13px; }
"""

_SCRIPT = """
(function () {
  "use strict";
  const table = document.getElementById("results");
  const body = table.tBodies[0];
  const cards = document.getElementById("cards");
  const rows = Array.from(body.rows);
  const shown = document.getElementById("shown");
  const headers = Array.from(table.tHead.rows[0].cells);
  headers.forEach(function (th, column) {
    th.querySelector("button").addEventListener("click", function () {
      const ascending = th.getAttribute("aria-sort") !== "ascending";
      headers.forEach(function (h) { h.removeAttribute("aria-sort"); });
      th.setAttribute("aria-sort", ascending ? "ascending" : "descending");
      const numeric = th.classList.contains("num");
      const key = function (row) { return row.cells[column].dataset.sort; };
      rows.sort(function (a, b) {
        let x = key(a), y = key(b);
        if (numeric) {
          x = x === "" ? NaN : Number(x);
          y = y === "" ? NaN : Number(y);
          if (isNaN(x) || isNaN(y)) { return isNaN(x) - isNaN(y); }  // blanks last
          return ascending ? x - y : y - x;
        }
        const order = x.localeCompare(y, undefined, {numeric: true});  // seed2 < seed10
        return ascending ? order : -order;
      });
      rows.forEach(function (row) {
        body.appendChild(row);
        cards.appendChild(document.getElementById(row.dataset.card));
      });
    });
  });
  const filter = document.getElementById("filter");
  filter.addEventListener("input", function () {
    const words = filter.value.toLowerCase().split(/\\s+/).filter(Boolean);
    let count = 0;
    rows.forEach(function (row) {
      const match = words.every(function (w) { return row.dataset.text.includes(w); });
      row.hidden = !match;
      document.getElementById(row.dataset.card).hidden = !match;
      count += match;
    });
    shown.textContent = count + " of " + rows.length + " shown";
  });
})();
"""

_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"
_WRAP = ("controller", "search")  # columns whose long labels wrap
_COLUMNS = (  # heading, numeric
    ("name", False),
    ("kind", False),
    ("body", False),
    ("controller", False),
    ("search", False),
    ("best fitness", True),
    ("evaluations", True),
    ("time (s)", True),
    ("seed", True),
    ("check", False),
    ("date", False),
)


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _sort_value(x: float | int | None) -> str:
    if x is None or isinstance(x, bool):
        return ""
    x = float(x)
    return (
        ""
        if math.isnan(x)
        else repr(x)
        if math.isfinite(x)
        else ("Infinity" if x > 0 else "-Infinity")
    )


def _row(result: Result, card: str) -> str:
    cells = [
        (result.name, result.name, f'<a href="#{card}">{_e(result.name)}</a>'),
        (result.kind, result.kind, None),
        (result.body, result.body, None),
        (result.controller, result.controller, None),
        (result.search, result.search, None),
        (_sort_value(result.best_fitness), result.best_text, None),
        (
            _sort_value(result.evaluations if isinstance(result.evaluations, int) else None),
            _short(result.evaluations),
            None,
        ),
        (_sort_value(result.time_s), _short(result.time_s), None),
        (_sort_value(_number(result.seed)), _short(result.seed), None),
        (
            result.verdict.state + " " + result.verdict.label,
            result.verdict.label,
            f'<span class="badge {result.verdict.state}">{_e(result.verdict.label)}</span>',
        ),
        (result.date, result.date, None),
    ]
    text = " ".join(
        str(v)
        for v in (
            result.name,
            result.kind,
            result.body,
            result.controller,
            result.search,
            result.verdict.label,
            result.folder,
            result.date,
        )
    ).lower()
    tds = []
    for (sort, shown, markup), (heading, numeric) in zip(cells, _COLUMNS, strict=True):
        cls = ' class="num"' if numeric else ' class="wrap"' if heading in _WRAP else ""
        tds.append(f'<td{cls} data-sort="{_e(sort)}">{markup or _e(shown)}</td>')
    return (
        f'<tr class="result-row" data-card="{card}" data-text="{_e(text)}">'
        + "".join(tds)
        + "</tr>"
    )


def _image(path: Path, caption: str, cls: str) -> str:
    uri = _data_uri(path)
    if uri is None:
        size = path.stat().st_size
        return f'<div class="absent">{_e(path.name)} is not a GIF or PNG image ({size} bytes)</div>'
    return (
        f'<figure><img class="{cls}" src="{uri}" alt="{_e(caption)}">'
        f"<figcaption>{_e(caption)}</figcaption></figure>"
    )


def _card(result: Result, card: str) -> str:
    media = []
    if result.motion is not None:
        media.append(_image(result.motion, "motion.gif", "motion"))
    else:
        how = (
            f"<br>To draw it: <code>python -m jaxmotion replay {_e(result.folder)} --gif "
            f"{_e(result.folder / 'motion.gif')}</code>"
            if result.kind == "run"
            else ""
        )
        media.append(
            '<div class="absent no-motion"><p>No motion: this folder has no motion.gif (the '
            "run had animation off: <code>--no-animation</code> or <code>[output] animation "
            f"= false</code>).{how}</p></div>"
        )
    for caption, path in result.plots:
        media.append(_image(path, caption, "plot"))
    for name in result.missing_plots:
        media.append(f'<div class="absent">No learning plot: {_e(name)} is missing</div>')
    figures = "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in result.figures)
    checks = []
    for heading, check in result.verdict.details:
        if not isinstance(check, dict):
            continue
        items = "".join(
            f'<li class="{"ok" if ok else "no"}">{_e(text)}</li>'
            for text, ok in _table(check.get("criteria")).items()
        )
        numbers = ", ".join(f"{k} {_short(v)}" for k, v in _table(check.get("figures")).items())
        state = "passed" if check.get("passed") else "failed"
        checks.append(
            f"<details{' open' if state == 'failed' else ''}><summary>{_e(heading)}: "
            f"{_e(check.get('name', 'check'))} {state}</summary>"
            f'<ul class="criteria">{items}</ul><div class="checkfigures">{_e(numbers)}</div>'
            "</details>"
        )
    return (
        f'<section class="card" id="{card}">'
        f"<h2>{_e(result.name)} "
        f'<span class="badge {result.verdict.state}">{_e(result.verdict.label)}</span></h2>'
        f'<div class="path">{_e(result.folder)} · {_e(result.kind)} · {_e(result.body)} · '
        f"{_e(result.controller)} · {_e(result.search)}</div>"
        f'<div class="media">{"".join(media)}</div>'
        f"<dl>{figures}</dl>{''.join(checks)}</section>"
    )


def gallery_html(results: Sequence[Result], *, sources: Sequence[str | Path] = ()) -> str:
    """The page for these results: a sortable, filterable table on top, then one card per
    result (its motion, learning plots, check and key figures), all in one HTML string."""
    ids = [f"result-{i}" for i in range(1, len(results) + 1)]
    num = ' class="num"'
    heads = "".join(
        f'<th{num if numeric else ""}><button type="button">{_e(name)}</button></th>'
        for name, numeric in _COLUMNS
    )
    rows = "".join(_row(r, i) for r, i in zip(results, ids, strict=True))
    cards = "".join(_card(r, i) for r, i in zip(results, ids, strict=True))
    written = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    n = len(results)
    where = ", ".join(str(s) for s in sources)
    return (
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<meta http-equiv="Content-Security-Policy" content="{_CSP}">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>jaxmotion gallery: {n} result{'s' if n != 1 else ''}</title>"
        f"<style>{_STYLE}</style></head><body>"
        "<header><h1>jaxmotion gallery</h1>"
        f'<p class="sub">{n} result{"s" if n != 1 else ""} from {_e(where)} · written {written}. '
        "Click a heading to sort; type to filter (name, body, controller, check...).</p>"
        '<div class="controls"><input id="filter" type="search" '
        'placeholder="Filter: e.g. star_man passed" aria-label="Filter the results">'
        f'<span id="shown">{n} of {n} shown</span></div>'
        f'<div class="tablewrap"><table id="results"><thead><tr>{heads}</tr></thead>'
        f"<tbody>{rows}</tbody></table></div>"
        f'</header><main id="cards">{cards}</main><script>{_SCRIPT}</script></body></html>\n'
    )


def check_page_path(out: str | Path) -> Path:
    """The page's path, checked before anything is read or written.

    **Raises:** `ConfigError` naming `--out`, its value and what is allowed."""
    text = str(out)
    if not text.strip() or "\x00" in text:
        raise ConfigError(f"--out = {text!r}; allowed: a path to an .html file")
    path = Path(out)
    if path.is_dir():
        raise ConfigError(f"--out = {text!r} is a folder; allowed: a file path (e.g. gallery.html)")
    if path.suffix.lower() not in PAGE_SUFFIXES:
        raise ConfigError(f"--out = {text!r}; allowed: an HTML file (.html or .htm)")
    if not path.parent.is_dir():
        raise ConfigError(f"--out = {text!r}: the folder {str(path.parent)!r} does not exist")
    return path


def write_gallery(paths: Sequence[str | Path], out: str | Path) -> tuple[Path, int]:
    """Write the gallery page of `paths` (results folders, or folders holding them) to
    `out`: every folder is read first, then the page is written to a temporary file beside
    `out` and renamed into place, so a failure leaves nothing half-written. Returns the
    page's path and the number of results on it.

    **Raises:** `ConfigError` for a bad `out`, a path that is not a results folder or a
    file in one that does not parse."""
    page = check_page_path(out)
    results = [read_result(folder) for folder in find_results(paths)]
    text = gallery_html(results, sources=paths)
    fd, tmp = tempfile.mkstemp(prefix=f".{page.name}.", suffix=".partial", dir=page.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)  # mkstemp's file is private; a page is for sharing
        os.replace(tmp, page)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return page, len(results)


__all__ = ["Result", "find_results", "gallery_html", "read_result", "write_gallery"]
