"""`python -m jaxmotion gallery`: one self-contained HTML page of results folders, checked
in a real headless browser (Chromium's engine, Qt WebEngine, from PyPI's PySide6-WebEngine):
it loads, shows every result with its images decoded, sorts and filters, and logs nothing
to the console; and the errors for what is not a results folder."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_compose import COMPONENT, compose_raw

from jaxmotion._cli.config import ConfigError
from jaxmotion._cli.gallery import WHAT_A_RESULTS_FOLDER_HOLDS, write_gallery
from jaxmotion._cli.main import _gallery, _parser
from jaxmotion.experiment import parse_config, run_experiment

ROOT = Path(__file__).resolve().parents[1]
BROWSER_TIMEOUT_S = 60  # the page loads in about a second; a hung browser fails the test
INSTALL = "pip install -e '.[test]'  (or: pip install 'PySide6-WebEngine>=6.12')"

# test_compose's tiny search (one compilation for every run of it: the same shapes, other
# seeds) and its composite: in one suite run, the persistent compilation cache serves
# whichever of the two files runs second. With a check, so that the verdicts show.
CHECKED = {**COMPONENT, "check": {"motion": "shuffle"}}


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Results folders of every kind: a sweep (a folder holding two runs, seeds 0 and 1,
    no motion), a run with its motion.gif, a two-stage run and a composite of the sweep's
    two runs."""
    from jaxmotion._cli.compose import parse_compose_config, run_compose

    base = tmp_path_factory.mktemp("gallery")
    sweep = base / "sweep"
    parts = [
        run_experiment(
            parse_config({**CHECKED, "seed": s}, name=f"part{s}"),
            directory=sweep,
            progress=False,
        )
        for s in (0, 1)
    ]
    animated = {**CHECKED, "seed": 2, "output": {"animation": True, "fps": 25}}
    gif = run_experiment(
        parse_config(animated, name="with-gif"), directory=base / "gif", progress=False
    )
    staged = run_experiment(
        parse_config({**CHECKED, "stage": [{"name": "kick"}, {"name": "roll"}]}, name="staged"),
        directory=base / "staged",
        progress=False,
    )
    raw = compose_raw(parts)  # test_compose's composite: its script, the two runs in turn
    duo = run_compose(
        parse_compose_config(raw, name="duo"), directory=base / "duo", animation=False
    )
    return {"sweep": sweep, "parts": parts, "gif": gif, "staged": staged, "duo": duo}


# Runs in a subprocess: Qt owns its process's event loop and environment. Prints one JSON
# object: whether the page loaded, what `probe` (JavaScript) returned, the console messages.
BROWSER = textwrap.dedent(
    """
    import json, os, sys
    os.environ["QT_QPA_PLATFORM"] = "offscreen"  # headless: no display
    os.environ["QTWEBENGINE_DISABLE_SANDBOX"] = "1"  # CI runs as root
    os.environ["QTWEBENGINE_CHROMIUM_FLAGS"] = (
        "--no-sandbox --disable-gpu --disable-quic --no-first-run "
        "--disable-background-networking --disable-component-update --disable-sync"
    )
    from PySide6.QtCore import QEventLoop, QTimer, QUrl
    from PySide6.QtWebEngineCore import QWebEnginePage, QWebEngineProfile
    from PySide6.QtWidgets import QApplication

    app = QApplication([])
    console = []

    class Page(QWebEnginePage):
        def javaScriptConsoleMessage(self, level, message, line, source):
            console.append({"level": level.name, "message": message, "line": line})

    profile = QWebEngineProfile()  # off the record: a fresh profile, nothing on disk
    page = Page(profile)  # (the profile must outlive the page: keep both named)
    out = {"loaded": None, "result": None}
    loop = QEventLoop()

    def done(key):
        return lambda value: (out.__setitem__(key, value), loop.quit())

    page.loadFinished.connect(done("loaded"))
    page.load(QUrl.fromLocalFile(sys.argv[1]))
    QTimer.singleShot(30000, loop.quit)
    loop.exec()
    if out["loaded"]:
        page.runJavaScript(sys.argv[2], 0, done("result"))
        QTimer.singleShot(30000, loop.quit)
        loop.exec()
    out["console"] = console
    print(json.dumps(out), flush=True)
    os._exit(0)  # Qt's teardown of a headless page has nothing to tell
    """
)

# What the test reads of the page, after clicking "best fitness" and typing a filter.
PROBE = """
JSON.stringify((function () {
  const visible = (sel) => Array.from(document.querySelectorAll(sel)).filter((e) => !e.hidden);
  const rows = () => Array.from(document.querySelectorAll("#results tbody tr"));
  const cells = (row) => Array.from(row.cells).map((c) => c.textContent.trim());
  const out = {
    title: document.title,
    rows: rows().map(cells),
    cards: Array.from(document.querySelectorAll("section.card")).map((c) => c.id),
    images: Array.from(document.images).map((i) => ({
      cls: i.className, card: i.closest("section").id, complete: i.complete,
      width: i.naturalWidth, height: i.naturalHeight})),
    noMotion: Array.from(document.querySelectorAll(".no-motion")).map(
      (e) => [e.closest("section").id, e.textContent]),
    badges: rows().map((r) => r.querySelector(".badge").className),
  };
  const headings = Array.from(document.querySelectorAll("#results th"));
  const best = headings.findIndex((th) => th.textContent.trim() === "best fitness");
  headings[best].querySelector("button").click();
  out.ascending = rows().map((r) => r.cells[best].dataset.sort);
  out.cardOrder = Array.from(document.querySelectorAll("section.card")).map((c) => c.id);
  out.rowOrder = rows().map((r) => r.dataset.card);
  headings[best].querySelector("button").click();
  out.descending = rows().map((r) => r.cells[best].dataset.sort);
  const filter = document.getElementById("filter");
  filter.value = "composite";
  filter.dispatchEvent(new Event("input"));
  out.filtered = [visible("#results tbody tr").length, visible("section.card").length,
                  document.getElementById("shown").textContent];
  return out;
})())
"""


def browse(page: Path, probe: str) -> dict:
    """Load `page` in headless Chromium (Qt WebEngine) and run `probe` in it."""
    if importlib.util.find_spec("PySide6") is None or (
        importlib.util.find_spec("PySide6.QtWebEngineCore") is None
    ):
        pytest.fail(
            "no headless browser for the gallery test: Qt WebEngine (Chromium, from PyPI's "
            f"PySide6-WebEngine) is not installed; install it with {INSTALL}"
        )
    run = subprocess.run(
        [sys.executable, "-c", BROWSER, str(page), probe],
        capture_output=True,
        text=True,
        timeout=BROWSER_TIMEOUT_S,
    )
    lines = [line for line in run.stdout.splitlines() if line.startswith("{")]
    if run.returncode != 0 or not lines:
        pytest.fail(
            f"the headless browser (Qt WebEngine) did not run (exit {run.returncode}); it needs "
            f"{INSTALL} and the system libraries Chromium uses (on Debian: apt-get install -y "
            f"libnss3 libxkbcommon0 libgl1 libegl1 libfontconfig1):\n{run.stderr[-3000:]}"
        )
    return json.loads(lines[-1])


def summary(folder: Path) -> dict:
    return json.loads((folder / "summary.json").read_text())


def test_the_page_shows_every_result_in_a_headless_browser(folders, tmp_path):
    """The CLI writes one page for a sweep's folder, a run with a GIF (named twice: shown
    once), a multi-stage run and a composite; in the browser it loads with no console
    message, has one table row and one card per result, every image (the motion, the
    learning plots) decodes, a folder without motion.gif says so, the table holds each
    summary's figures, and sorting and filtering work."""
    page = tmp_path / "page.html"
    gif, staged, duo = folders["gif"], folders["staged"], folders["duo"]
    paths = [folders["sweep"], gif, staged, duo, gif]
    cli = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "gallery", *map(str, paths), "--out", str(page)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert cli.returncode == 0, cli.stderr
    assert cli.stdout.strip() == f"{page} (5 results)"
    assert [p.name for p in tmp_path.iterdir()] == ["page.html"]  # nothing else left
    text = page.read_text()
    assert "http://" not in text and "https://" not in text  # nothing to fetch: self-contained

    seen = browse(page, PROBE)
    assert seen["loaded"] is True
    assert seen["console"] == []  # no error, no warning, nothing at all
    got = seen["result"]
    assert isinstance(got, str), seen
    got = json.loads(got)
    assert got["title"] == "jaxmotion gallery: 5 results"

    # One row and one card per result, in the order given (the sweep's by name).
    expected = [*folders["parts"], gif, staged, duo]
    names = [summary(f)["name"] for f in expected]
    assert [row[0] for row in got["rows"]] == names
    assert got["cards"] == [f"result-{i}" for i in range(1, 6)]
    # The table holds each summary's figures: kind, body, controller, evaluations, seed.
    for row, folder in zip(got["rows"], expected, strict=True):
        s = summary(folder)
        assert row[2] == "star_man"
        assert row[6] == str(s["evaluations"])
        assert row[8] == str(s["seed"])
    assert [row[1] for row in got["rows"]] == ["run", "run", "run", "2 stages", "composite"]
    assert [row[3] for row in got["rows"]][:4] == ["time_bsr"] * 4
    assert got["rows"][4][3] == "sequence of time_bsr"
    for row, folder in zip(got["rows"][:3], expected[:3], strict=True):
        assert float(row[5]) == pytest.approx(summary(folder)["best_fitness"], rel=1e-3)
    # Check verdicts: a run's and the stages' from summary.json, the composite's phases.
    for badge, row, folder in zip(got["badges"][:4], got["rows"][:4], expected[:4], strict=True):
        check = summary(folder)["check"]
        state = "passed" if check["passed"] else "failed"
        assert badge == f"badge {state}"
        assert row[9] == f"shuffle: {state}"
    phases = summary(duo)["best"]["checks"].values()
    assert got["rows"][4][9] == f"{sum(c['passed'] for c in phases)} of 2 phases pass"

    # Every image decoded: the one motion.gif and each learning plot (a stage's each).
    motions = [i for i in got["images"] if i["cls"] == "motion"]
    plots = [i for i in got["images"] if i["cls"] == "plot"]
    assert [m["card"] for m in motions] == ["result-3"]
    assert sorted(p["card"] for p in plots) == [
        "result-1",
        "result-2",
        "result-3",
        "result-4",
        "result-4",
        "result-5",
    ]
    for image in got["images"]:
        assert image["complete"] and image["width"] > 0 and image["height"] > 0, image
    # The folders without motion.gif say so.
    assert [card for card, _ in got["noMotion"]] == ["result-1", "result-2", "result-4", "result-5"]
    for _, words in got["noMotion"]:
        assert "no motion.gif" in words

    # Sorting by best fitness: ascending, then descending; the stages (no single best
    # fitness) last both times; the cards follow the rows.
    values = [float(v) for v in got["ascending"] if v != ""]
    assert values == sorted(values) and len(values) == 4 and got["ascending"][-1] == ""
    values = [float(v) for v in got["descending"] if v != ""]
    assert values == sorted(values, reverse=True) and got["descending"][-1] == ""
    assert got["cardOrder"] == got["rowOrder"]
    # Filtering: only the composite's row and card stay.
    assert got["filtered"] == [1, 1, "1 of 5 shown"]


def test_what_is_not_a_results_folder_is_refused_naming_the_path(folders, tmp_path):
    """A missing path, a file, a folder holding no results folder, a results folder
    without summary.json or with a broken one: each is refused naming the path and what a
    results folder holds, and nothing is written."""
    out = tmp_path / "out"
    out.mkdir()
    page = out / "gallery.html"
    lonely = tmp_path / "empty"
    lonely.mkdir()
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    shutil.copy(folders["gif"] / "config.toml", unfinished)
    broken = tmp_path / "broken"
    shutil.copytree(folders["gif"], broken)
    (broken / "summary.json").write_text("{not json")
    cases = [
        (tmp_path / "nowhere", "not a results folder (no such folder)"),
        (folders["gif"] / "summary.json", "not a results folder (a file)"),
        (lonely, "not a results folder (no config.toml) and holds none"),
        (unfinished, "not a complete results folder (no summary.json"),
    ]
    for path, words in cases:
        with pytest.raises(ConfigError) as e:
            write_gallery([folders["sweep"], path], page)
        assert str(e.value).startswith(f"{path}: {words}")
        assert WHAT_A_RESULTS_FOLDER_HOLDS in str(e.value)
    with pytest.raises(ConfigError, match=f"{broken / 'summary.json'}: not valid JSON"):
        write_gallery([broken], page)
    assert list(out.iterdir()) == []


def test_bad_out_is_refused_and_a_failed_write_leaves_nothing(folders, tmp_path, monkeypatch):
    """--out must be an HTML file in an existing folder (checked before anything is read);
    a write that fails leaves neither the page nor its temporary file."""
    sweep = folders["sweep"]
    for out, words in [
        (tmp_path, "is a folder; allowed: a file path"),
        (tmp_path / "page.txt", "allowed: an HTML file (.html or .htm)"),
        (tmp_path / "no" / "page.html", "does not exist"),
    ]:
        args = _parser().parse_args(["gallery", str(sweep), "--out", str(out)])
        with pytest.raises(ConfigError) as e:
            _gallery(args)
        assert str(e.value).startswith(f"--out = {str(out)!r}") and words in str(e.value)
    page = tmp_path / "page.html"

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_gallery([sweep], page)
    assert list(tmp_path.iterdir()) == []


def test_the_cli_exits_2_naming_a_path_that_is_not_a_results_folder(tmp_path):
    """`python -m jaxmotion gallery PATH` with a bad PATH: exit 2, the path and what a
    results folder holds on stderr, no page."""
    missing = tmp_path / "missing"
    run = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "gallery", str(missing), "--out", "x.html"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert run.returncode == 2
    assert run.stderr.startswith(f"error: {missing}: not a results folder (no such folder)")
    assert "holds config.toml and summary.json" in run.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_folder_of_results_lists_them_by_name_numbers_as_numbers(tmp_path):
    """A folder holding results folders (a sweep's) stands for them: by name, seed2 before
    seed10; hidden folders (a running search's, a sweep task's), folders without
    config.toml and files skipped; a folder named twice (itself and through its parent)
    listed once."""
    from jaxmotion._cli.gallery import find_results

    for name in ("run-seed10", "run-seed2", ".run-seed3.task", "sweep.md-dir"):
        (tmp_path / name).mkdir()
    for name in ("run-seed10", "run-seed2", ".run-seed3.task"):
        (tmp_path / name / "config.toml").write_text('name = "run"\n')
    (tmp_path / "sweep.md").write_text("| table |\n")
    found = find_results([tmp_path, tmp_path / "run-seed2"])
    assert found == [tmp_path / "run-seed2", tmp_path / "run-seed10"]
