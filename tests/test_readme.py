"""The README's first two commands are the ones CI runs."""

import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]


def readme_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    start = lines.index("```bash") + 1
    return [line.split("#")[0].strip() for line in lines[start:start + 2]]


def test_ci_runs_the_readme_commands():
    install, tests = readme_commands()
    assert install.startswith("pip install") and "estim demo" in install
    assert tests.startswith("pytest")
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert install in ci, "the README's install+demo command must appear in .ci/run verbatim"
    assert tests in ci, "the README's test command must appear in .ci/run verbatim"
