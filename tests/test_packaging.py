import subprocess
import sys

from tests.conftest import REPO, run_overgrid


def test_robot_client_imports_no_renderer_no_opencv_no_compiler() -> None:
    code = (
        "import sys, common.client, common.mapfiles, services.client_cli, services.cli;"
        "heavy = [m for m in ('cv2', 'mujoco', 'numba') if m in sys.modules];"
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_cli_lists_every_command() -> None:
    result = run_overgrid("--help")
    assert result.returncode == 0
    for command in ("camera-sim", "depth", "fusion", "map", "health"):
        assert command in result.stdout


def test_a_command_whose_extra_is_not_installed_names_the_extra() -> None:
    """On a robot's base install, ``overgrid eval`` and ``overgrid fusion`` ended in a
    ModuleNotFoundError traceback."""
    for command, module, extra in (("eval", "cv2", "depth"), ("fusion", "scipy", "fusion")):
        code = (
            f"import sys; sys.modules[{module!r}] = None;"  # as if not installed
            f"from services.cli import main; main([{command!r}])"
        )
        result = subprocess.run(
            [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert result.stderr.strip() == (
            f"overgrid {command} needs {module}, which this install lacks: "
            f"pip install 'overgrid[{extra}]'"
        )


def test_an_unknown_command_is_one_line_naming_it() -> None:
    """It printed the usage to stdout and nothing on stderr."""
    result = run_overgrid("frobnicate")
    assert result.returncode == 2 and not result.stdout
    assert result.stderr == "overgrid: no command 'frobnicate' (overgrid --help lists them)\n"
