"""code_version: the commit and whether the code differs from it; redrawn results/ figures do not count."""

import subprocess

import pytest

from morefree_jax import provenance


def _git(repo, *args):
    subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                   capture_output=True)


@pytest.fixture
def checkout(tmp_path, monkeypatch):
    (tmp_path / "results").mkdir()
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "results" / "table.md").write_text("| a |\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "first")
    monkeypatch.setattr(provenance, "_REPO", tmp_path)
    provenance.code_version.cache_clear()
    yield tmp_path
    provenance.code_version.cache_clear()


def test_redrawn_results_leave_the_code_clean(checkout):
    (checkout / "results" / "table.md").write_text("| b |\n")
    version = provenance.code_version()
    assert version["dirty"] is False and len(version["commit"]) == 40


def test_a_changed_source_file_is_dirty(checkout):
    (checkout / "code.py").write_text("x = 2\n")
    assert provenance.code_version()["dirty"] is True
