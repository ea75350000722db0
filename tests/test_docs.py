"""The documentation site: every command has its generated page, the pages say what --help says, the
figures are small, and `mkdocs build --strict` (links and anchors checked) passes offline."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS))

from gen_cli import command_pages  # noqa: E402

from ari_sfm.cli import main  # noqa: E402


def _every_command(group: click.Group, words=()):
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        yield (*words, name), cmd
        if isinstance(cmd, click.Group):
            yield from _every_command(cmd, (*words, name))


def test_every_command_has_a_generated_page_with_its_options():
    pages = {p.words: p for p in command_pages()}
    commands = dict(_every_command(main))
    assert set(commands) == set(pages) - {()}, "a command without a page, or a page without a command"
    for words, cmd in commands.items():
        page = pages[words].markdown
        assert page.startswith(f"# ari-sfm {' '.join(words)}\n"), words
        for p in cmd.params:
            if isinstance(p, click.Option) and not p.hidden and p.name != "help":
                assert f"`{p.opts[-1]}`" in page, (words, p.opts)  # every option in the table
        assert " ".join(cmd.help.split()[:8]) in " ".join(page.split()), words  # its help text
    index = pages[()].markdown
    assert all(f"({p.path.removeprefix('cli/')})" in index for p in pages.values() if p.words)


def test_the_config_option_is_documented_on_its_commands_pages():
    pages = {p.words: p.markdown for p in command_pages()}
    for command in ("calibrate", "run", "particles", "self-calibrate"):
        assert "`--config`" in pages[(command,)] and "override" in pages[(command,)]
    assert "`--config`" not in pages[("detect",)]


def test_figures_are_small_and_every_one_is_used():
    figures = sorted((DOCS / "figures").glob("*.png"))
    assert figures, "docs/figures/ is empty: run docs/gen_figures.py"
    text = "".join(p.read_text() for p in DOCS.rglob("*.md")) + (ROOT / "README.md").read_text()
    for png in figures:
        assert png.stat().st_size < 200_000, png
        assert png.name in text, f"{png.name} is not shown on any page"


def test_site_builds_strict_and_offline(tmp_path):
    """mkdocs build --strict (a broken link, anchor or docstring reference fails it) with the network closed
    to Python (a proxy to a closed port); the pages load nothing from another host."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "http_proxy": "http://127.0.0.1:9",
           "https_proxy": "http://127.0.0.1:9", "HTTP_PROXY": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9"}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    site = tmp_path / "site"
    for words in [p.words for p in command_pages() if p.words]:
        assert (site / "cli" / "-".join(words) / "index.html").is_file(), words
    home = (site / "index.html").read_text()
    assert "figures/report.png" in home
    for page in site.rglob("*.html"):
        loaded = re.findall(r'<(?:script|link|img)[^>]+(?:src|href)="(https?://[^"]+)"', page.read_text())
        assert not loaded, (page, loaded[:3])  # no font, script or style fetched from elsewhere
    api = (site / "api" / "factors" / "index.html").read_text()
    assert "RigGraph" in api and "from_dataset" in api  # the factor graph's API from its docstrings


def test_readme_quick_start_commands_are_kept():
    readme = (ROOT / "README.md").read_text()
    assert "## Quick start" in readme
    assert "bash scripts/setup.sh && .venv/bin/ari-sfm run datasets/sample -o out/sample" in readme
    assert "bash scripts/setup.sh --tests && .venv/bin/python -m pytest -q" in readme
