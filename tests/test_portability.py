"""Guards for the Jetson target (linux-aarch64, JetPack 6's Python 3.10) and for light clients.

- the code needs nothing newer than Python 3.10 (vermin: syntax and standard-library modules);
- the complete dependency set less torch (JetPack brings its own) resolves for
  ``manylinux_2_35_aarch64`` / cp310 from wheels alone (JetPack 6 is Ubuntu 22.04, glibc 2.35);
- a wheel built from the tree carries the profiles, and bare profile names resolve from it;
- ``h3edge query`` and ``h3edge profile report`` start without torch, numba or Open3D.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
TARGET_PYTHON = "3.10"
TARGET_ENV = {  # environment markers of a Jetson on JetPack 6
    "python_version": "3.10", "python_full_version": "3.10.12", "platform_machine": "aarch64",
    "sys_platform": "linux", "platform_system": "Linux", "os_name": "posix",
    "implementation_name": "cpython", "platform_python_implementation": "CPython",
}
# glibc 2.17 .. 2.35 (pip takes the tags literally, so list every one a JetPack 6 Python accepts)
VERMIN = [sys.executable, "-c", "import sys; from vermin.main import main; sys.exit(main())"]
TARGET_PLATFORMS = [f"manylinux_2_{v}_aarch64" for v in range(17, 36)] + ["manylinux2014_aarch64", "linux_aarch64"]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def jetson_requirements(project: dict, extras: tuple[str, ...] = ("eval", "oak", "view")) -> list[str]:
    """Runtime dependencies plus ``extras``, markers evaluated for the Jetson, torch left out."""
    from packaging.markers import default_environment
    from packaging.requirements import Requirement

    env = {**default_environment(), **TARGET_ENV, "extra": ""}
    reqs = list(project["dependencies"])
    for e in extras:
        reqs += project["optional-dependencies"][e]
    out = []
    for text in reqs:
        r = Requirement(text)
        if r.name == "torch" or (r.marker is not None and not r.marker.evaluate(env)):
            continue
        r.marker = None
        out.append(str(r))
    return out


def test_jetson_requirements_drop_x86_only_packages():
    proj = _pyproject()
    reqs = jetson_requirements(proj)
    names = {r.split(">")[0].split("=")[0].split("<")[0].split("[")[0] for r in reqs}
    assert "open3d" in names and "open3d-cpu" not in names and "torch" not in names
    assert "tomli" in names  # Python 3.10 has no tomllib


def test_code_needs_nothing_newer_than_python_310():
    r = subprocess.run(VERMIN + [f"--target={TARGET_PYTHON}-", "--violations", "--no-tips",
                        "--no-parse-comments", str(ROOT / "h3edge"), str(ROOT / "tests")],
                       capture_output=True, text=True)
    assert r.returncode == 0, f"Python > {TARGET_PYTHON} needed:\n{r.stdout}\n{r.stderr}"


def test_vermin_catches_a_tomllib_only_import(tmp_path):
    """The guard above has teeth: a bare ``import tomllib`` fails it, the version-checked import passes."""
    bad, good = tmp_path / "bad.py", tmp_path / "good.py"
    bad.write_text("import tomllib\n")
    good.write_text(
        "import sys\nif sys.version_info >= (3, 11):\n    import tomllib\nelse:\n    import tomli as tomllib\n"
    )
    run = VERMIN + [f"--target={TARGET_PYTHON}-", "--violations", "--no-tips"]
    assert subprocess.run(run + [str(bad)], capture_output=True).returncode != 0
    assert subprocess.run(run + [str(good)], capture_output=True).returncode == 0


def _resolve_for_jetson(reqs: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pip", "install", "--dry-run", "--ignore-installed", "--only-binary=:all:",
           "--python-version", TARGET_PYTHON, "--implementation", "cp", "--target", str(tmp_path / "t"),
           "--report", str(tmp_path / "report.json"), "--quiet", "--disable-pip-version-check"]
    for p in TARGET_PLATFORMS:
        cmd += ["--platform", p]
    return subprocess.run(cmd + reqs, capture_output=True, text=True, timeout=600)


def _unreachable(r: subprocess.CompletedProcess) -> bool:
    text = r.stdout + r.stderr
    return any(s in text for s in ("Failed to establish a new connection", "Temporary failure in name resolution",
                                   "Network is unreachable", "No route to host"))


def test_dependency_set_resolves_for_jetson_from_wheels(tmp_path):
    reqs = jetson_requirements(_pyproject())
    r = _resolve_for_jetson(reqs, tmp_path)
    if r.returncode != 0 and _unreachable(r) and not os.environ.get("CI"):
        pytest.skip("package index unreachable")
    assert r.returncode == 0, f"not installable on linux-aarch64 / cp310 from wheels:\n{r.stderr[-3000:]}"
    names = {i["metadata"]["name"].lower() for i in json.loads((tmp_path / "report.json").read_text())["install"]}
    assert {"numba", "onnxruntime", "eclipse-zenoh", "open3d", "depthai", "tomli", "rosbags", "rerun-sdk"} <= names


def test_resolution_guard_refuses_an_x86_only_wheel(tmp_path):
    """The guard has teeth: embreex (x86-64 wheels only) as a dependency fails it."""
    r = _resolve_for_jetson(["embreex>=2.17"], tmp_path)
    if _unreachable(r) and not os.environ.get("CI"):
        pytest.skip("package index unreachable")
    assert r.returncode != 0 and "embreex" in r.stderr


def test_wheel_ships_profiles_and_bare_names_resolve(tmp_path):
    """A non-editable install (wheel into a folder outside the tree) finds every profile by name."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet",
                    "--disable-pip-version-check", "-w", str(tmp_path / "dist"), str(ROOT)], check=True,
                   capture_output=True, timeout=300)
    wheel = next((tmp_path / "dist").glob("h3edge-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {Path(n).stem for n in names if n.startswith("h3edge/profiles/") and n.endswith(".toml")}
    assert {"x86-cpu", "orin-agx", "orin-nano", "paper-reference"} <= shipped
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    code = (f"import h3edge, h3edge.config as c; assert h3edge.__file__.startswith({str(site)!r}), h3edge.__file__; "
            "print(c.load_profile('orin-agx').name, c.load_profile('orin-nano').name)")
    env = {**os.environ, "PYTHONPATH": str(site)}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["orin-agx", "orin-nano"]
    r = subprocess.run([sys.executable, "-m", "h3edge", "serve", "--profile", "orin-agx", "--help"], cwd=tmp_path,
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0 and "--state-dir" in r.stdout, r.stderr


@pytest.mark.parametrize("argv", [
    ["query", "status", "--timeout", "0.3", "--no-multicast"],
    ["profile", "report", "RUN_DIR"],
], ids=["query", "profile-report"])
def test_clients_start_without_torch_numba_or_open3d(argv, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "profile.json").write_text(json.dumps({"profile": "x86-cpu", "components": {}}))
    argv = [str(run_dir) if a == "RUN_DIR" else a for a in argv]
    code = (f"import sys\nfrom h3edge.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('torch', 'numba', 'open3d', 'onnxruntime') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout + r.stderr
