"""MkDocs hook: the figures the gallery shows are taken from results/ as `tracklab reproduce`
wrote them (no copies under docs/ to keep in step)."""

import re
from pathlib import Path

from mkdocs.structure.files import File


def on_files(files, config):
    docs = Path(config["docs_dir"])
    root = docs.parent
    wanted = set()
    for page in docs.glob("*.md"):
        wanted.update(re.findall(r"\]\((results/[^)\s]+\.png)\)", page.read_text()))
    for rel in sorted(wanted):
        if (root / rel).is_file():
            files.append(File(rel, str(root), config["site_dir"], config["use_directory_urls"]))
    return files
