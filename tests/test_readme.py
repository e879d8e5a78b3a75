"""The README and docs/usage.md as a user reads them: every command and Python snippet runs as printed.

Each ```bash or ```python block of those pages is one test, run in document order in a folder that holds what the
pages assume (``planning_ct.nii.gz`` and ``cbct.nii.gz``, a simulated CT/CBCT pair; ``ct_dicom/`` and
``cbct_dicom/``, the same as DICOM series with their own frames of reference), after the page's earlier blocks (a
block may use what an earlier one wrote, as a reader would; those marked slow or skipped are nobody's prerequisite).
Bash blocks run in ``bash -e`` with ``monai-rigidreg`` and ``python`` meaning this interpreter and this checkout;
Python blocks run in this process. A block is preceded by an HTML comment where it is not a default-suite test:

- ``<!-- test: slow -->``: runs with ``python -m pytest -m slow`` (minutes of CPU);
- ``<!-- test: needs TOOL -->``: skipped where ``TOOL`` is not on PATH (transformix, dciodvfy);
- ``<!-- test: skip: REASON -->``: not run, for the reason given (the set-up commands: ``.ci/run`` runs them).

Also: the README stays a front page (at most 250 lines, its test command as ``.ci/run`` runs it), and its links and
the usage page's point at files that exist.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import KNOWN_MOTION, write_dicom_series

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
USAGE = ROOT / "docs" / "usage.md"
PAGES = (README, USAGE)
TEST_COMMAND = 'pip install torch==2.13.0 && pip install -e ".[test]" && python -m pytest'
"""The README's test command, which ``.ci/run`` runs verbatim."""

_BLOCK = re.compile(r"(?:<!-- test: (?P<mark>[^>]*?) -->\n)?```(?P<lang>[a-z]*)\n(?P<code>.*?)```", re.S)


def blocks(page: Path) -> list[tuple[str, str, str, int]]:
    """``(language, code, mark, line)`` of every fenced block of ``page`` with a language."""
    text = page.read_text(encoding="utf-8")
    return [(m["lang"], m["code"], m["mark"] or "", text.count("\n", 0, m.start("code")))
            for m in _BLOCK.finditer(text) if m["lang"]]


def _runnable(mark: str) -> bool:
    """Whether a block with ``mark`` runs in this environment (slow ones aside)."""
    if mark.startswith("needs "):
        return shutil.which(mark.split()[1]) is not None
    return not mark.startswith("skip:")


def _params() -> list:
    out = []
    for page in PAGES:
        for index, (_, _, mark, line) in enumerate(blocks(page)):
            marks = [pytest.mark.slow] if mark == "slow" else []
            if mark.startswith("needs ") and not _runnable(mark):
                marks.append(pytest.mark.skip(reason=f"{mark.split()[1]} is not installed"))
            elif mark.startswith("skip:"):
                marks.append(pytest.mark.skip(reason=mark[5:].strip()))
            out.append(pytest.param(page, index, id=f"{page.name}:{line}", marks=marks))
    return out


@pytest.fixture(scope="module")
def workdirs(tmp_path_factory):
    """One folder per page (its blocks run there in order): the pages' input files, and a ``bin/`` with
    ``monai-rigidreg`` and ``python`` for this interpreter and checkout."""
    import SimpleITK as sitk

    from monai_rigidreg.simulation import simulate_pair

    base = tmp_path_factory.mktemp("docs")
    pair = simulate_pair(base / "pair", phantom="shepp-logan-asym", params=KNOWN_MOTION, seed=4, device="cpu")
    bin_dir = base / "bin"
    bin_dir.mkdir()
    for name, run in (("monai-rigidreg", '-m monai_rigidreg.cli "$@"'), ("python", '"$@"')):
        (bin_dir / name).write_text(f'#!/bin/sh\nexec "{sys.executable}" {run}\n')
        (bin_dir / name).chmod(0o755)
    ct, cbct = (sitk.ReadImage(pair[k]) for k in ("fixed", "moving"))
    folders = {}
    for page in PAGES:
        work = base / page.stem
        work.mkdir()
        shutil.copy(pair["fixed"], work / "planning_ct.nii.gz")
        shutil.copy(pair["moving"], work / "cbct.nii.gz")
        write_dicom_series(ct, work / "ct_dicom", "1.2.826.0.1.3680043.2.1125.10",
                           frame_of_reference_uid="1.2.826.0.1.3680043.2.1125.11")
        write_dicom_series(cbct, work / "cbct_dicom", "1.2.826.0.1.3680043.2.1125.20",
                           frame_of_reference_uid="1.2.826.0.1.3680043.2.1125.21")
        folders[page] = work
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
           "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    return folders, env, {page: set() for page in PAGES}


def _run_block(lang: str, code: str, work: Path, env: dict, page: Path) -> None:
    if lang == "python":
        before = Path.cwd()
        os.chdir(work)
        try:
            exec(compile(code, str(page), "exec"), {"__name__": "__docs__"})  # noqa: S102 - the documented snippet
        finally:
            os.chdir(before)
        return
    assert lang == "bash", f"a {lang} block: mark it, or make it bash or python"
    done = subprocess.run(["bash", "-e", "-c", code], cwd=work, env=env, capture_output=True, text=True,
                          encoding="utf-8", errors="replace", timeout=900)
    assert done.returncode == 0, f"exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"


@pytest.mark.parametrize(("page", "index"), _params())
def test_every_command_and_snippet_runs_as_printed(page, index, workdirs):
    folders, env, ran = workdirs
    found = blocks(page)
    for earlier, (lang, code, mark, _) in enumerate(found[:index]):  # what a reader ran before, where not run yet
        if earlier not in ran[page] and mark != "slow" and _runnable(mark):
            _run_block(lang, code, folders[page], env, page)
            ran[page].add(earlier)
    lang, code, _, _ = found[index]
    _run_block(lang, code, folders[page], env, page)
    ran[page].add(index)


def test_readme_is_a_front_page_with_its_test_command_as_ci_runs_it():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    assert TEST_COMMAND in text and TEST_COMMAND in (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    for heading in ("## Set up and run", "## Register your own CT and CBCT", "### The couch shifts", "### Exit codes",
                    "## From Python", "## Results", "## Status", "## Where to go next"):
        assert f"\n{heading}\n" in text, heading
    # the "known motion on my own CT" check is on the front page, not only in --help
    assert "monai-rigidreg demo --phantom planning_ct.nii.gz --motion" in text


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_links_point_at_files_and_headings_that_exist():
    """Relative links of the README and the usage page (docs/serve.md arrives with the DICOM service's branch: that
    line is plain text, not a link)."""
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            if target.startswith(("http://", "https://")):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            assert file.exists(), f"{page.name}: {target}"
            if anchor:
                headings = re.findall(r"^#+ (.+)$", file.read_text(encoding="utf-8"), re.M)
                assert anchor in {_anchor(h) for h in headings}, f"{page.name}: {target}"


def test_every_block_is_bash_or_python_and_the_pages_run_commands():
    found = {page.name: [lang for lang, *_ in blocks(page)] for page in PAGES}
    assert all(lang in ("bash", "python") for langs in found.values() for lang in langs), found
    assert found["README.md"].count("python") == 1 and found["usage.md"].count("bash") >= 10
