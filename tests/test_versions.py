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
