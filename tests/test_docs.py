"""The documentation site: ``mkdocs build --strict`` passes, the quickstart on its front page
runs and prints what the page says, and the pages agree with the README and the CLI."""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = DOCS / "pages"
CONFIG = DOCS / "mkdocs.yml"


def fenced_blocks(text: str, language: str) -> list[list[str]]:
    """The lines of every fenced code block of ``language`` in a Markdown text, in order."""
    blocks, current = [], None
    for line in text.splitlines():
        if current is None and line.strip() == f"```{language}":
            current = []
        elif current is not None and line.strip() == "```":
            blocks.append(current)
            current = None
        elif current is not None:
            current.append(line)
    return blocks


def section(text: str, heading: str) -> str:
    """The Markdown from ``## heading...`` up to the next ``## `` heading."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## " + heading))
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
    return "\n".join(lines[start:end])


def test_mkdocs_build_strict(tmp_path):
    """The site builds with --strict (every warning an error: broken links, missing nav
    pages, docstrings griffe cannot parse), into a directory outside the repository."""
    site = tmp_path / "site"
    default_site = DOCS / "site"  # where a build without -d would write
    existed = default_site.exists()
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(CONFIG), "-d", str(site)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    for page in ("index.html", "concepts/index.html", "contact-model/index.html",
                 "data-formats/index.html", "cli/index.html", "fitting/index.html",
                 "api/simulation/index.html", "api/fitting/index.html", "api/data/index.html",
                 "api/replay/index.html"):
        assert (site / page).is_file(), page
    # The API reference is generated from the docstrings of the public API.
    api = (site / "api" / "simulation" / "index.html").read_text()
    for name in ("estim.simulate", "estim.Params", "estim.load_scene", "estim.event_sensitivities"):
        assert f'id="{name}"' in api, name
    assert 'id="estim.fit"' in (site / "api" / "fitting" / "index.html").read_text()
    assert 'id="estim.read_tracks_csv"' in (site / "api" / "data" / "index.html").read_text()
    assert default_site.exists() == existed, "the build wrote into the repository"


def test_front_page_shows_the_readme_commands():
    readme = (ROOT / "README.md").read_text().splitlines()
    start = readme.index("```bash") + 1
    commands = readme[start:start + 2]
    first = fenced_blocks((PAGES / "index.md").read_text(), "bash")[0]
    assert first[:2] == commands, "docs/pages/index.md must show the README's two commands verbatim"


def test_quickstart_fit_in_five_lines(monkeypatch, capsys):
    """Runs the quickstart block of the front page (from the repository root, as the page
    says) and checks it prints the numbers in its final comment.

    In-process on purpose: the fit compiles the same programs as ``estim fit`` on the same
    data (``tests/test_fit_cli.py``), so in a full run the compile is paid once.
    """
    text = section((PAGES / "index.md").read_text(), "Quickstart")
    (block,) = fenced_blocks(text, "python")
    code = [line for line in block if line.strip() and not line.startswith("import ")]
    assert len(code) <= 5, f"the quickstart promises a fit in five lines, it has {len(code)}"
    printed = re.search(r"#\s*(.+)$", code[-1]).group(1)

    monkeypatch.chdir(ROOT)
    exec(compile("\n".join(block), str(PAGES / "index.md"), "exec"), {"__name__": "quickstart"})
    out = capsys.readouterr().out.strip().splitlines()[-1]

    def numbers(s):
        return [float(x) for x in re.findall(r"-?\d+\.\d+", s)]

    assert re.sub(r"[-\d.]+", "#", out) == re.sub(r"[-\d.]+", "#", printed), (out, printed)
    assert numbers(out) == pytest.approx(numbers(printed), abs=2e-4), (out, printed)


def test_cli_page_covers_every_command_and_option():
    from estim.app._cli import build_parser

    page = (PAGES / "cli.md").read_text()

    def walk(parser, prefix):
        for action in parser._actions:
            if action.option_strings and action.dest != "help":
                long = max(action.option_strings, key=len)
                yield prefix, long
            elif action.dest != "help" and not action.option_strings and action.choices is None:
                yield prefix, action.dest  # a positional argument
            if action.choices and hasattr(action.choices, "items"):
                for name, sub in action.choices.items():
                    yield from walk(sub, f"{prefix} {name}")

    missing = []
    for command, option in walk(build_parser(), "estim"):
        if command != "estim" and f"## {command.split()[0]} {command.split()[1]}" not in page:
            missing.append(f"section '## {command.split()[0]} {command.split()[1]}'")
        if f"`{option}" not in page:
            missing.append(f"{command} {option}")
    assert not missing, f"docs/pages/cli.md does not document: {sorted(set(missing))}"


def test_no_links_to_the_old_docs_paths():
    """The pages moved from docs/*.md to docs/pages/*.md."""
    old = re.compile(r"docs/(?:contact-model|fitting)\.md")
    files = [ROOT / "README.md", *DOCS.rglob("*.md"), *DOCS.rglob("*.py"),
             *(ROOT / "estim").glob("*.py"), *(ROOT / "tests").glob("*.py")]
    stale = [f"{f.relative_to(ROOT)}:{i + 1}" for f in files if f.is_file()
             for i, line in enumerate(f.read_text().splitlines()) if old.search(line)]
    assert not stale, f"paths to the pages' old place in docs/ (they are in docs/pages/ now): {stale}"


def test_architecture_contact_law_example(monkeypatch):
    """The one-file contact law of the architecture page runs as written, and a ball thrown
    back into a riser leaves it as the law says (by hand: vx -> e_wall * 2 m/s, vz -> mu_t
    vz), where the seed's law would give it e * 2 m/s."""
    import numpy as np

    monkeypatch.chdir(ROOT)
    block = fenced_blocks(section((PAGES / "architecture.md").read_text(), "How to add a contact law"),
                          "python")[0]
    ns: dict = {}
    exec("\n".join(block), ns)  # noqa: S102 - the page's own example
    estim, scene = ns["estim"], ns["scene"]
    assert ns["traj"].complete
    for s, e_riser in ((scene, 0.3), (scene.with_law(estim.FactorLaw()), 0.7)):
        ball = estim.Params.for_ball(s, "golf", e=0.7, mu_t=0.98, velocity=(-2.0, 0.0, 0.0),
                                     position=(0.9, 0.0, 1.7))
        ev = estim.simulate(s, ball, 0.4, max_segments=400).events
        pre, post = np.asarray(ev.velocity_pre[0]), np.asarray(ev.velocity_post[0])
        assert pre[0] == -2.0  # it meets the riser (normal +x) before any tread
        np.testing.assert_allclose(post, [e_riser * 2.0, 0.0, 0.98 * pre[2]], rtol=0, atol=1e-12)
