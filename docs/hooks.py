"""MkDocs hooks (mkdocs.yml ``hooks:``): the command reference generated from the click command line at every
build (docs/gen_cli.py), never written into the source tree."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from gen_cli import command_pages  # noqa: E402

NAV_TITLE = "Commands"  # the nav entry mkdocs.yml leaves for the generated pages


def on_config(config, **kwargs):
    """Put every command's page under the nav's "Commands" entry."""
    pages = command_pages()
    entries = [{"Overview": "cli/index.md"}] + [{f"ari-sfm {p.title}": p.path} for p in pages if p.words]
    for item in config["nav"] or []:
        if isinstance(item, dict) and NAV_TITLE in item:
            item[NAV_TITLE] = entries
            break
    else:
        raise ValueError(f"mkdocs.yml: nav has no {NAV_TITLE!r} entry for the generated command pages")
    config["extra"]["_cli_pages"] = pages
    return config


def on_files(files, config, **kwargs):
    """Add the generated pages to the site's files."""
    from mkdocs.structure.files import File

    for page in config["extra"]["_cli_pages"]:
        files.append(File.generated(config, page.path, content=page.markdown))
    return files
