"""The documentation: the paths the code and the docs name exist, the generated reference pages are
current, and the README keeps its promises (the two commands, its size, a container example whose
status page can be reached)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED_DOCS = ROOT.parent / "shared" / "docs"

#: ``docs/....md`` as code, tests, tools and documents name it; ``shared/docs/...`` names the
#: project's manuals beside the repository.
_DOC_PATH = re.compile(r"(?<![\w/.-])((?:shared/)?docs/[\w./-]+\.md)")


def _tracked_text_files() -> list[Path]:
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    suffixes = {".py", ".md", ".toml", ".yml", ".yaml", ".sh", ".service", ""}
    return [ROOT / name for name in listed.splitlines() if Path(name).suffix in suffixes and (ROOT / name).is_file()]


def test_every_docs_path_named_in_the_repository_exists() -> None:
    """A note moved or renamed leaves no reference to its old place behind (code comments, error
    messages, tests, tools, other pages)."""
    missing: list[str] = []
    for path in _tracked_text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for match in _DOC_PATH.finditer(text):
            named = match.group(1)
            if named.startswith("shared/"):
                if SHARED_DOCS.is_dir() and not (SHARED_DOCS / named.removeprefix("shared/docs/")).exists():
                    missing.append(f"{path.relative_to(ROOT)}: {named}")
            elif not (ROOT / named).exists():
                missing.append(f"{path.relative_to(ROOT)}: {named}")
    assert missing == []
