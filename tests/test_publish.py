"""Reports move into their folder as one unit (store/atomic.py publish_files): a reader, or a kill at
any moment, never finds a report.md beside files of another set, and a user's files stay."""

import os
import stat
import subprocess
import sys
import textwrap

import pytest

from sonarset import SonarSetError
from sonarset.store.atomic import publish_files


def _write_set(tag: str):
    def write(folder):
        (folder / "metrics.json").write_text(f'{{"set": "{tag}"}}\n')
        (folder / "fig.png").write_bytes(tag.encode())
        (folder / "report.md").write_text(f"# report {tag}\n")
    return write


def _asides(parent):
    return [p for p in parent.iterdir() if p.name.startswith(".")]


def test_a_new_folder_is_the_whole_set_at_once(tmp_path):
    out = publish_files(tmp_path / "eval-out", _write_set("a"), last="report.md")
    assert sorted(p.name for p in out.iterdir()) == ["fig.png", "metrics.json", "report.md"]
    assert (out / "report.md").read_text() == "# report a\n"
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~_umask()  # as mkdir makes it, not private
    assert _asides(tmp_path) == []


def test_an_existing_folder_gets_the_new_set_and_keeps_its_own_files(tmp_path):
    out = tmp_path / "demo-out"
    publish_files(out, _write_set("old"), last="report.md")
    (out / "test.zarr").mkdir()  # the demo's store lives beside its report
    publish_files(out, _write_set("new"), last="report.md")
    assert (out / "report.md").read_text() == "# report new\n"
    assert (out / "metrics.json").read_text() == '{"set": "new"}\n'
    assert (out / "test.zarr").is_dir()
    assert _asides(tmp_path) == []


def test_a_failed_write_leaves_the_old_set_whole(tmp_path):
    out = tmp_path / "eval-out"
    publish_files(out, _write_set("old"), last="report.md")

    def broken(folder):
        (folder / "metrics.json").write_text("{}")
        raise RuntimeError("figure failed")

    with pytest.raises(RuntimeError):
        publish_files(out, broken, last="report.md")
    assert (out / "report.md").read_text() == "# report old\n"
    assert (out / "metrics.json").read_text() == '{"set": "old"}\n'
    assert _asides(tmp_path) == []


def test_a_kill_while_moving_in_never_leaves_a_report_beside_another_sets_files(tmp_path):
    """SIGKILL after the first file of the new set moved in: the old report.md is already gone, so
    nothing looks complete; the next writer removes the dead one's leftovers and lands its set."""
    out = tmp_path / "eval-out"
    publish_files(out, _write_set("old"), last="report.md")
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {os.fspath(tmp_path)!r})
        from sonarset.store.atomic import publish_files
        import test_sets
        real = os.replace
        def replace_then_die(a, b):
            real(a, b)
            os.kill(os.getpid(), signal.SIGKILL)
        os.replace = replace_then_die
        publish_files({os.fspath(out)!r}, test_sets.write, last="report.md")
    """)
    (tmp_path / "test_sets.py").write_text(textwrap.dedent("""
        def write(folder):
            (folder / "metrics.json").write_text('{"set": "new"}\\n')
            (folder / "report.md").write_text("# report new\\n")
    """))
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == -9, res.stderr
    assert not (out / "report.md").exists()  # no report beside the new metrics.json
    assert (out / "metrics.json").read_text() == '{"set": "new"}\n'
    assert len([p for p in _asides(tmp_path) if p.is_dir()]) == 1  # the dead writer's aside
    publish_files(out, _write_set("next"), last="report.md")
    assert (out / "report.md").read_text() == "# report next\n"
    assert [p for p in _asides(tmp_path) if p.is_dir()] == []


def test_a_file_where_the_folder_should_be_is_refused(tmp_path):
    (tmp_path / "eval-out").write_text("not a folder")
    with pytest.raises(SonarSetError, match="eval-out: exists and is not a folder"):
        publish_files(tmp_path / "eval-out", _write_set("a"), last="report.md")
    assert (tmp_path / "eval-out").read_text() == "not a folder"
    assert [p for p in _asides(tmp_path) if p.is_dir()] == []


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
