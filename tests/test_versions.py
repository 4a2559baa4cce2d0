"""The provenance every results record carries, and the lock file the README installs."""

from pathlib import Path

from nimbus.versions import cpu_isa, software_versions

ROOT = Path(__file__).resolve().parents[1]


def test_versions_name_the_libraries_and_the_isa():
    v = software_versions()
    for key in ("nimbus", "python", "torch", "numpy", "opencv-contrib-python-headless", "pycolmap", "cpu_isa"):
        assert key in v and v[key], key
    assert cpu_isa() in {"avx512", "avx2", "generic", "unknown"}


def test_lock_file_pins_every_direct_dependency_and_the_ci_uses_it():
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt line {line!r} is not an exact pin"
            pins[name.lower()] = version
    for dep in ("torch", "numpy", "opencv-contrib-python-headless", "pycolmap", "scikit-image", "onnxruntime",
                "colour-science", "pandas", "pytest", "dask", "distributed"):
        assert dep in pins, f"{dep} is not pinned in constraints.txt"
    assert pins["torch"] == "2.13.0"
    ci, readme = (ROOT / ".ci" / "run").read_text(), (ROOT / "README.md").read_text()
    assert '-c constraints.txt -e ".[test]"' in ci and '-c constraints.txt -e ".[test]"' in readme


def _git(root, *args):
    import subprocess

    subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True,
                   env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                        "GIT_COMMITTER_EMAIL": "t@t", "HOME": str(root), "PATH": __import__("os").environ["PATH"]})


def test_source_commit_names_the_commit_and_a_changed_code_file(tmp_path):
    import shutil

    import pytest

    from nimbus.versions import commit_of

    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    assert commit_of(tmp_path) is None  # not a checkout: an installed wheel records no commit
    (tmp_path / "nimbus").mkdir()
    (tmp_path / "nimbus" / "a.py").write_text("x = 1\n")
    (tmp_path / "notes.txt").write_text("text\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "c")
    head = commit_of(tmp_path)
    assert head is not None and len(head) == 12 and int(head, 16) >= 0
    (tmp_path / "nimbus" / "new.py").write_text("y = 2\n")  # untracked: not the commit's code, not a change
    (tmp_path / "notes.txt").write_text("edited\n")  # outside the code folders
    assert commit_of(tmp_path) == head
    (tmp_path / "nimbus" / "a.py").write_text("x = 2\n")
    assert commit_of(tmp_path) == head + "+modified"
    assert not (tmp_path / ".git" / "index.lock").exists()


def test_records_carry_the_source_commit_in_a_checkout():
    import shutil

    from nimbus.versions import source_commit

    commit = source_commit()
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        assert commit is None and "nimbus_commit" not in software_versions()
    else:
        assert commit is not None and software_versions()["nimbus_commit"] == commit
