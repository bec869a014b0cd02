"""`benchmarks/device_wheels.py`: pobax's requirements carried as wheels to a machine without a package index."""

import importlib.metadata as md
import importlib.util
import zipfile
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "device_wheels", Path(__file__).resolve().parents[1] / "benchmarks" / "device_wheels.py")
device_wheels = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(device_wheels)


def _wheel(folder: Path, name: str, version: str) -> Path:
    """A pure-Python wheel of one module, as a build backend writes one."""
    path = folder / f"{name}-{version}-py3-none-any.whl"
    info = f"{name}-{version}.dist-info"
    files = {f"{name}/__init__.py": "VALUE = 1\n",
             f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n",
             f"{info}/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    files[f"{info}/RECORD"] = "".join(f"{f},,\n" for f in [*files, f"{info}/RECORD"])
    with zipfile.ZipFile(path, "w") as z:
        for f, text in files.items():
            z.writestr(f, text)
    return path


def test_install_takes_only_what_the_interpreter_lacks(tmp_path, capsys):
    wheels, target = tmp_path / "whl", tmp_path / "site"
    wheels.mkdir()
    _wheel(wheels, "pobax_carried_probe", "1.0")
    _wheel(wheels, "equinox", "0.0.1")  # installed here: its version is kept, the wheel's stays out
    assert device_wheels.main(["install", "--from", str(wheels), "--target", str(target)]) == 0
    assert "installing 1 of 2 wheels: pobax-carried-probe" in capsys.readouterr().out
    assert (target / "pobax_carried_probe" / "__init__.py").is_file()
    assert not (target / "equinox").exists()


def test_plan_carries_pobax_requirements_at_the_versions_here_and_not_the_accelerators_stack():
    names = ["jax", "jaxlib", "numpy", "scipy", "ml_dtypes", "opt_einsum", "pobax-bench", "Equinox", "pandas", "tyro"]
    assert device_wheels.plan(names, skip={"pandas"}) == [f"Equinox=={md.version('equinox')}",
                                                          f"tyro=={md.version('tyro')}"]
    assert device_wheels.wheel_name("docstring_parser-0.18.0-py3-none-any.whl") == "docstring-parser"


def test_installed_lists_the_interpreters_distributions(capsys):
    assert device_wheels.main(["installed"]) == 0
    assert f"equinox=={md.version('equinox')}" in capsys.readouterr().out.splitlines()


@pytest.mark.parametrize("argv, message", [
    (["install", "--from", "{tmp}", "--target", "{tmp}/site"], "holds no wheels"),
    (["fetch", "--to", "{tmp}/w", "--families", "craftax", "atari"], "--families atari: no such family"),
    (["fetch", "--to", "{tmp}/w", "--skip-installed", "{tmp}/missing.txt"], "cannot be read"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        device_wheels.main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "w").exists()


def test_the_trace_finds_what_pobax_imports_and_no_family_it_was_not_given():
    parser = device_wheels.Parser()
    names = set(map(device_wheels.canonical, device_wheels.traced_distributions((), Path(__file__).resolve().parents[1], parser)))
    assert {"equinox", "optax", "tyro", "pandas", "memax", "jax"} <= names  # memax: built by the S6 cell
    assert not {"craftax", "brax", "navix"} & names
