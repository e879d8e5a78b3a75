"""The output-folder checks (monai_rigidreg.io.volumes.check_output_dir): a folder that cannot be written is refused
before anything is read.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest
from conftest import last_line, listing, run_cli

from monai_rigidreg.core.errors import InputError


def test_an_output_folder_that_cannot_be_written_is_refused_before_anything_is_read(pair, tmp_path, capsys,
                                                                                   with_small_network, monkeypatch):
    """Found by access(2) up front (it sees read-only mounts and immutable folders, even for root), not after the
    registration with a wrong reason; here access(2) is made to answer no for one folder, and any read fails the
    test."""
    from monai_rigidreg.io import volumes as io
    from monai_rigidreg.registration import files

    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(io.os, "access", lambda p, mode, **kw: False if Path(p) == locked else real_access(p, mode,
                                                                                                         **kw))
    monkeypatch.setattr(files, "load_volume", lambda *a, **k: pytest.fail("read before the output check"))
    base = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"]]
    code, err = run_cli(capsys, [*base, "--output-dir", locked])
    assert code == 2 and last_line(err).endswith(f"{locked}: the output folder is not writable"), err
    code, err = run_cli(capsys, [*base, "--output-dir", locked / "sub"])
    assert code == 2 and f"cannot create the output folder: {locked} is not writable" in last_line(err), err
    assert listing(tmp_path) == ["locked"]
    # a link to a folder elsewhere: staging replaces the folder where it lies, so the link's own parent is not asked
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    link = locked / "link"
    link.symlink_to(elsewhere)
    from monai_rigidreg.io import check_output_dir

    assert check_output_dir(link) == link
    (elsewhere / "inner").mkdir()
    with pytest.raises(InputError, match="cannot create the output folder: .*locked is not writable"):
        check_output_dir(locked / "new")


def test_an_immutable_output_folder_is_refused_up_front(pair, tmp_path, with_small_network, capsys):
    """The same with a real immutable folder (chattr +i; root may write anywhere else), where the file system and
    the user allow setting it."""
    import shutil

    locked = tmp_path / "locked"
    locked.mkdir()
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(locked)], capture_output=True).returncode:
        pytest.skip("chattr +i is not available here (needs root and a file system with the immutable flag)")
    try:
        t = time.perf_counter()
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"],
                                     "--output-dir", locked / "sub"])
        assert code == 2 and f"{locked} is not writable" in last_line(err), err
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"],
                                     "--output-dir", locked])
        assert code == 2 and "the output folder is not writable" in last_line(err), err
        assert time.perf_counter() - t < 5.0  # no registration ran
    finally:
        subprocess.run(["chattr", "-i", str(locked)], check=True)
    assert listing(tmp_path) == ["locked"]
