"""``report.html`` of ``monai-rigidreg evaluate``: the tables match summary.json and report.md, failed and flagged
cases come first, every overlay it shows exists (and stays small), the markup nests, and it renders in Chromium."""

from __future__ import annotations

import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.cli import build_parser
from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.evaluation import evaluate_datalist, write_html_report
from monai_rigidreg.evaluation.evaluate import load_datalist, true_params
from monai_rigidreg.evaluation.overlays import OVERLAY_MAX_BYTES, OverlayGallery, needs_attention
from monai_rigidreg.evaluation.report import CaseResult

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}

ERRORS = [[10.0, 0, 0, 0, 0, 0], [0.0] * 6, [0.5, 0, 0, 0, 0, 0]]
"""What the stub network gets wrong on the three tiny cases (mm, degrees): case 0 fails (TRE 10 mm), case 1 is
exact but flagged (a false alarm), case 2 succeeds (TRE 0.5 mm)."""
FLAGS = [(0.9, False), (0.2, True), (0.8, False)]


class StubRegistrar:
    """Stands in for ``RigidRegistrar``: the truth plus :data:`ERRORS`, with :data:`FLAGS` (no network)."""

    def __init__(self, datalist: Path) -> None:
        self.items, _ = load_datalist(datalist)
        self.calls = 0

    def __call__(self, fixed, moving, **kwargs):
        i = self.calls % len(self.items)
        self.calls += 1
        truth = true_params(self.items[i], Grid.from_sitk(fixed).center())
        conf, flagged = FLAGS[i]
        return SimpleNamespace(params=truth + np.asarray(ERRORS[i]), confidence=conf, flagged=flagged,
                               timings={"network": 0.01})


class PageParser(HTMLParser):
    """Tables (id -> rows of (row attributes, cell texts)), image sources, links; end tags checked against the
    open elements, so that mis-nested markup is an error."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.tables: dict[str, list[tuple[dict, list[str]]]] = {}
        self.imgs: list[str] = []
        self.hrefs: list[str] = []
        self.scripts = 0
        self._table: str | None = None
        self._row: tuple[dict, list[str]] | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a.get("src", ""))
        if tag in ("a", "link") and "href" in a:
            self.hrefs.append(a["href"])
        if tag == "script":
            self.scripts += 1
        if tag == "table":
            self._table = a.get("id", f"table{len(self.tables)}")
            self.tables[self._table] = []
        elif tag == "tr" and self._table is not None:
            self._row = (a, [])
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1] if self.stack else 'nothing'} at {self.getpos()}")
        else:
            self.stack.pop()
        if tag in ("td", "th") and self._cell is not None and self._row is not None:
            self._row[1].append("".join(self._cell).strip())
            self._cell = None
        elif tag == "tr" and self._row is not None and self._table is not None:
            self.tables[self._table].append(self._row)
            self._row = None
        elif tag == "table":
            self._table = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def parse(path: Path) -> PageParser:
    p = PageParser()
    p.feed(path.read_text(encoding="utf-8"))
    p.close()
    assert not p.errors, p.errors
    assert p.stack == [], f"unclosed elements: {p.stack}"
    return p


def markdown_tables(text: str) -> list[list[list[str]]]:
    """Rows (cells) of each table of report.md, header first, separator left out."""
    tables, cur = [], None
    for line in text.splitlines():
        if line.startswith("|"):
            if cur is None:
                cur = []
                tables.append(cur)
            if not line.startswith("|---"):
                cur.append([c.strip() for c in line.strip().strip("|").split("|")])
        else:
            cur = None
    return tables


@pytest.fixture(scope="module")
def evaluated(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval_html")
    res = evaluate_datalist(tiny_dataset, ["network", "sitk"], out, registrar=StubRegistrar(tiny_dataset),
                            progress=False, max_overlays=0)
    return res, out


def test_html_report_tables_match_summary_and_markdown(evaluated, tiny_dataset):
    res, out = evaluated
    html_path = out / "report.html"
    assert res["paths"]["html"] == html_path and html_path.is_file()
    page = parse(html_path)
    assert page.scripts == 0
    assert not [h for h in page.hrefs + page.imgs if "://" in h or h.startswith("//")], "no network references"
    text = html_path.read_text(encoding="utf-8")
    assert str(Path(tiny_dataset).resolve()) in text and "monai-rigidreg" in text
    # the summary tables hold exactly report.md's cells
    md = markdown_tables((out / "report.md").read_text(encoding="utf-8"))
    summary_ids = ["table-translations", "table-rotations", "table-overall", "table-flag"]
    assert [k for k in page.tables if k != "table-cases"] == summary_ids
    assert [[cells for _, cells in page.tables[k]] for k in summary_ids] == md
    # ... and summary.json's numbers
    data = json.loads((out / "summary.json").read_text())
    s = data["summary"]
    overall = {cells[0]: cells for _, cells in page.tables["table-overall"][1:]}
    for method in ("network", "sitk"):
        assert overall[method][1] == str(s[method]["n"]) == "3"
        assert overall[method][2] == f"{s[method]['tre_mean_mm']:.2f}"
        assert overall[method][4] == f"{100 * s[method]['success_rate']:.0f}%"
    t1 = {(c[0], c[1]): c for _, c in page.tables["table-translations"][1:]}
    mean, sd = s["network"]["conditions"]["All cases"]["mae"]["tx"]
    assert t1[("network", "All cases")][3] == f"{mean:.2f} ± {sd:.2f}"
    flag = {c[0]: c for _, c in page.tables["table-flag"][1:]}
    assert flag["network"][1:] == [str(s["network"]["flag"][k]) for k in
                                   ("failures", "failures_flagged", "successes", "successes_flagged")]
    assert s["network"]["flag"] == {"failures": 1, "failures_flagged": 0, "successes": 2, "successes_flagged": 1}


def test_html_report_lists_failed_and_flagged_cases_first(evaluated):
    res, out = evaluated
    page = parse(out / "report.html")
    header, *rows = page.tables["table-cases"]
    cols = header[1]
    assert cols[:10] == ["#", "case id", "method", "group", "motion condition", "TRE (mm)", "success",
                         "confidence", "flagged", "runtime (s)"]
    cases = json.loads((out / "summary.json").read_text())["cases"]
    assert len(rows) == len(cases) == 6
    problem = []
    for attrs, cells in rows:
        c = cases[int(cells[0])]
        assert (cells[1], cells[2]) == (c["case_id"], c["method"])
        assert cells[5] == f"{c['tre_mm']:.2f}"
        assert cells[6] == ("yes" if c["tre_mm"] < 2.0 else "no")
        bad = c["tre_mm"] >= 2.0 or bool(c["extra"].get("flagged"))
        assert bad == any(k in attrs.get("class", "").split() for k in ("fail", "flag"))
        problem.append(bad)
    assert problem == sorted(problem, reverse=True), "failed and flagged rows first"
    # problem rows by decreasing TRE (the stub's 10 mm failure among them: SimpleITK's own failures on these tiny
    # pairs vary with its thread count, so the worst row may be one of its); its flagged false alarm is listed too
    tres = [float(cells[5]) for (_, cells), bad in zip(rows, problem) if bad and cells[5] != "nan"]
    assert tres == sorted(tres, reverse=True)
    assert any(cells[2] == "network" and cells[5] == "10.00" and cells[6] == "no"
               for (_, cells), bad in zip(rows, problem) if bad)
    flagged_rows = [cells for _, cells in rows if cells[2] == "network" and cells[8] == "yes"]
    assert len(flagged_rows) == 1 and flagged_rows[0][7] == "0.20" and rows.index(
        next(r for r in rows if r[1] == flagged_rows[0])) < problem.count(True)
    assert [cells[8] for _, cells in rows if cells[2] == "sitk"] == ["–"] * 3  # no confidence check


def test_html_report_images_exist_and_are_small(evaluated):
    res, out = evaluated
    page = parse(out / "report.html")
    assert page.imgs, "the failed and the flagged network case have overlays"
    for src in page.imgs:
        assert not Path(src).is_absolute() and src.startswith("report_files/")
        f = out / src
        assert f.is_file(), src
        assert f.stat().st_size <= OVERLAY_MAX_BYTES
        img = sitk.ReadImage(str(f))
        assert img.GetNumberOfComponentsPerPixel() == 3 and np.ptp(sitk.GetArrayFromImage(img)) > 50
    # max_overlays=0: exactly the results that failed or were flagged, of any method (the network's in cases 0 and
    # 1, a SimpleITK failure too), and the network's results of a case where a baseline failed
    cases = res["cases"]
    problem = {c.case_id for c in cases if needs_attention(c)}
    expect = {i for i, c in enumerate(cases) if needs_attention(c) or (c.method == "network" and c.case_id in problem)}
    assert len([i for i in expect if cases[i].method == "network" and needs_attention(cases[i])]) == 2
    assert sorted(p.name for p in (out / "report_files").iterdir()) == sorted(Path(s).name for s in page.imgs)
    assert {int(Path(s).name[:5]) for s in page.imgs} == expect
    for src in page.imgs:  # each shown overlay is linked from its row
        assert src in page.hrefs
    assert "1 further result(s) without an overlay" in (out / "report.html").read_text(encoding="utf-8")


def test_overlay_cap_and_no_html(tiny_dataset, tmp_path):
    out = evaluate_datalist(tiny_dataset, ["network"], tmp_path / "one", registrar=StubRegistrar(tiny_dataset),
                            progress=False, max_overlays=1)
    assert len(list((tmp_path / "one" / "report_files").glob("*.png"))) == 3  # 2 problem cases + 1 other
    assert len(parse(out["paths"]["html"]).imgs) == 3
    # a second run into the same folder needs overwrite, and leaves only its own overlays
    with pytest.raises(OutputExistsError):
        evaluate_datalist(tiny_dataset, ["network"], tmp_path / "one", registrar=StubRegistrar(tiny_dataset),
                          progress=False, max_overlays=0)
    evaluate_datalist(tiny_dataset, ["network"], tmp_path / "one", registrar=StubRegistrar(tiny_dataset),
                      progress=False, max_overlays=0, overwrite=True)
    assert len(list((tmp_path / "one" / "report_files").glob("*.png"))) == 2
    out = evaluate_datalist(tiny_dataset, ["network"], tmp_path / "none", registrar=StubRegistrar(tiny_dataset),
                            progress=False, html=False)
    assert "html" not in out["paths"] and (tmp_path / "none" / "report.md").is_file()
    assert not (tmp_path / "none" / "report.html").exists() and not (tmp_path / "none" / "report_files").exists()
    args = build_parser().parse_args(["evaluate", "--datalist", "d.json", "--output-dir", "o", "--no-html",
                                      "--max-overlays", "5"])
    assert (args.html, args.max_overlays) == (False, 5)
    assert build_parser().parse_args(["evaluate", "--datalist", "d.json", "--output-dir", "o"]).html is True


def test_a_failed_evaluation_leaves_no_overlays(tiny_dataset, tmp_path):
    class Breaks(StubRegistrar):
        def __call__(self, fixed, moving, **kwargs):
            if self.calls == 1:  # case 0's overlay is written by now
                raise RuntimeError("boom")
            return super().__call__(fixed, moving, **kwargs)

    with pytest.raises(RuntimeError, match="boom"):
        evaluate_datalist(tiny_dataset, ["network"], tmp_path / "a" / "b", registrar=Breaks(tiny_dataset),
                          progress=False)
    assert not (tmp_path / "a").exists()


def test_an_evaluation_replaces_only_an_earlier_report_and_only_when_it_completes(tiny_dataset, tmp_path):
    """A folder holding other files is refused, with or without overwrite (the user's cases.csv was replaced); an
    overwrite that fails (or is interrupted) leaves the earlier report, overlays included, as it was."""
    user = tmp_path / "user"
    user.mkdir()
    (user / "cases.csv").write_text("mine")
    (user / "notes.txt").write_text("mine too")
    for overwrite in (False, True):
        with pytest.raises(OutputExistsError):
            evaluate_datalist(tiny_dataset, ["network"], user, registrar=StubRegistrar(tiny_dataset), progress=False,
                              overwrite=overwrite)
    assert (user / "cases.csv").read_text() == "mine" and sorted(p.name for p in user.iterdir()) == [
        "cases.csv", "notes.txt"]
    report = tmp_path / "report"
    evaluate_datalist(tiny_dataset, ["network"], report, registrar=StubRegistrar(tiny_dataset), progress=False)
    before = {p.relative_to(report): p.read_bytes() for p in report.rglob("*") if p.is_file()}
    assert any(str(k).startswith("report_files") for k in before)

    class Breaks(StubRegistrar):
        def __call__(self, fixed, moving, **kwargs):
            if self.calls == 2:
                raise KeyboardInterrupt
            return super().__call__(fixed, moving, **kwargs)

    with pytest.raises(KeyboardInterrupt):
        evaluate_datalist(tiny_dataset, ["network"], report, registrar=Breaks(tiny_dataset), progress=False,
                          overwrite=True)
    after = {p.relative_to(report): p.read_bytes() for p in report.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "user"]  # no staging folder left


def test_every_case_s_ground_truth_is_checked_before_the_first_registration(tiny_dataset, tmp_path):
    """A malformed ground truth in the last item was found after all the others were registered (and their work
    lost, exit 1); it is refused first now, naming the item. A method named twice is refused too."""
    items = json.loads(Path(tiny_dataset).read_text())["training"]
    base = Path(tiny_dataset).parent
    for bad, expected in (({"params": "abc"}, "'params' must be six finite numbers"),
                          ({"params": [1, 2, 3]}, "'params' must be six finite numbers"),
                          ({"matrix": [[1, 0], [0, 1]]}, "'matrix' must be 4x4 finite numbers"),
                          ({"matrix": [[float("nan")] * 4] * 4}, "'matrix' must be 4x4 finite numbers"),
                          ({"matrix": np.diag([1.1, 1.0, 1.0, 1.0]).tolist()}, "'matrix' is not a rigid"),
                          ({}, "has no ground truth")):
        last = {k: v for k, v in items[-1].items() if k not in ("params", "matrix", "center")}
        edited = [*items[:-1], {**last, **bad}]
        datalist = tmp_path / "edited.json"
        datalist.write_text(json.dumps({"training": [{**it, "fixed": str(base / it["fixed"]),
                                                      "moving": str(base / it["moving"]),
                                                      "moving_fov": str(base / it["moving_fov"])} for it in edited]}))
        stub = StubRegistrar(tiny_dataset)
        with pytest.raises(InputError, match=rf"item {len(items) - 1} \(.*\)[: ].*{expected[:20]}"):
            evaluate_datalist(datalist, ["network"], tmp_path / "out", registrar=stub, progress=False)
        assert stub.calls == 0 and not (tmp_path / "out").exists()
    with pytest.raises(InputError, match="a method is named twice"):
        evaluate_datalist(tiny_dataset, ["network", "network"], None, registrar=StubRegistrar(tiny_dataset),
                          progress=False)


def _small_pair() -> tuple[sitk.Image, sitk.Image]:
    rng = np.random.default_rng(0)
    fixed = sitk.GetImageFromArray(rng.normal(size=(12, 16, 20)).astype(np.float32))
    fixed.SetSpacing((2.0, 2.0, 3.0))
    moving = sitk.GetImageFromArray(rng.normal(size=(10, 12, 12)).astype(np.float32))
    moving.SetSpacing((2.5, 2.5, 2.5))
    return fixed, moving


def test_html_report_escapes_text_and_writer_without_evaluation(tmp_path):
    fixed, moving = _small_pair()
    center = Grid.from_sitk(fixed).center()
    nasty = '<script>alert("x")</script> & co'
    cases = [
        CaseResult(nasty, "network", [15, 0, 0, 0, 0, 0], [14, 0, 0, 0, 0, 0], 1.0, 0.2, group="a<b",
                   extra={"confidence": 0.9, "flagged": False}),
        CaseResult("ok", "network", [0, 0, 0, 30, 0, 0], [0, 0, 0, 30, 0, 0], float("nan"), 0.2,
                   extra={"confidence": 0.7, "flagged": False}),
    ]
    gallery = OverlayGallery(tmp_path / "report_files", ["network"], max_others=0)
    gallery.add(fixed, moving, center, [(0, cases[0])])
    gallery.add(fixed, moving, center, [(1, cases[1])])
    assert list(gallery.images) == [1] and gallery.omitted == 1  # NaN TRE counts as failed
    path = write_html_report(cases, tmp_path / "report.html", overlays=gallery.images, datalist=None,
                             omitted_overlays=gallery.omitted)
    text = path.read_text(encoding="utf-8")
    assert "<script>" not in text and "&lt;script&gt;" in text
    page = parse(path)
    rows = page.tables["table-cases"][1:]
    assert [cells[1] for _, cells in rows] == ["ok", nasty]  # failed (NaN) first
    assert rows[1][1][3] == "a<b" and rows[0][1][5] == "nan"
    assert page.imgs == ["report_files/00001_ok_network.png"] and (tmp_path / page.imgs[0]).is_file()
    with pytest.raises(ValueError, match="max_others"):
        OverlayGallery(tmp_path, ["network"], max_others=-1)


def test_a_baseline_s_failure_gets_an_overlay_and_the_network_s_result_beside_it(tmp_path):
    """SimpleITK failed, the network did not: both results of that case get overlays (the baselines' failures had
    none); a case where every result succeeded counts against the cap, and only the network's is drawn."""
    fixed, moving = _small_pair()
    center = Grid.from_sitk(fixed).center()
    gallery = OverlayGallery(tmp_path / "report_files", ["network", "sitk"], max_others=1)
    ok = {"confidence": 0.9, "flagged": False}
    failed = [(0, CaseResult("a", "network", [5, 0, 0, 0, 0, 0], [5, 0, 0, 0, 0, 0], 0.1, 0.2, extra=ok)),
              (1, CaseResult("a", "sitk", [5, 0, 0, 0, 0, 0], [25, 0, 0, 0, 0, 0], 20.0, 0.2))]
    fine = [(2, CaseResult("b", "network", [5, 0, 0, 0, 0, 0], [5, 0, 0, 0, 0, 0], 0.1, 0.2, extra=ok)),
            (3, CaseResult("b", "sitk", [5, 0, 0, 0, 0, 0], [5, 0, 0, 0, 0, 0], 0.3, 0.2))]
    assert [p.name for p in gallery.add(fixed, moving, center, failed)] == ["00000_a_network.png", "00001_a_sitk.png"]
    assert [p.name for p in gallery.add(fixed, moving, center, fine)] == ["00002_b_network.png"]
    assert [p.name for p in gallery.add(fixed, moving, center, [(4, fine[0][1]), (5, fine[1][1])])] == []
    assert sorted(gallery.images) == [0, 1, 2] and gallery.omitted == 1


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="headless Chromium not installed (chromium / chromium-browser not "
                    "on PATH; e.g. apt-get install chromium): the page is not rendered")
def test_html_report_renders_in_headless_chromium(evaluated, tmp_path):
    _, out = evaluated
    shot = tmp_path / "report.png"
    cmd = [_chromium(), "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
           f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}", "--window-size=1200,2000",
           (out / "report.html").resolve().as_uri()]
    proc = subprocess.run(cmd, capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=180)
    assert shot.is_file(), f"no screenshot (rc {proc.returncode}): {proc.stderr[-2000:]}"
    arr = sitk.GetArrayFromImage(sitk.ReadImage(str(shot)))
    assert arr.shape[:2] == (2000, 1200)
    rgb = arr[..., :3].astype(np.int16)
    assert float(np.mean(rgb.min(axis=-1) < 200)) > 0.01, "the page renders as blank"  # text, tables, images
    # the overlays were loaded: saturated red/green pixels (the CT / CBCT colours) appear on the page
    overlay_px = (rgb[..., 0] - rgb[..., 2] > 100) | (rgb[..., 1] - rgb[..., 2] > 100)
    assert overlay_px.sum() > 500
