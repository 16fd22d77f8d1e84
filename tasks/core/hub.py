"""The commands we print for fetching model weights on a machine with internet (nothing here downloads anything).

huggingface_hub 2.x ships the ``hf`` command; ``huggingface-cli`` no longer exists.  ``hf download REPO [FILES]...
[--include PATTERN]... [--exclude PATTERN]... --local-dir DIR``: each ``--include`` / ``--exclude`` takes ONE pattern
(repeat the option for more; a second word after it would be read as a file name, and file names make ``hf`` ignore
every ``--include``), and explicit file names download only those files.  Arguments are shell-quoted.
"""
from __future__ import annotations

import shlex
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class HubSource:
    """Where a model is published on the Hugging Face hub: the repository, the files to take (all when empty) or
    glob patterns to include / exclude."""

    repo: str
    files: tuple[str, ...] = ()
    include: tuple[str, ...] = field(default=())
    exclude: tuple[str, ...] = field(default=())

    def command(self, local_dir: str | Path) -> str:
        """The ``hf download`` command that fills ``local_dir`` with this source."""
        return hf_download_command(self.repo, local_dir, self.files, self.include, self.exclude)


def hf_download_command(repo: str, local_dir: str | Path, files: Sequence[str] = (), include: Sequence[str] = (),
                        exclude: Sequence[str] = ()) -> str:
    """``hf download`` of ``files`` (or of the repo filtered by the ``include`` / ``exclude`` globs) into
    ``local_dir``, shell-quoted; ValueError when files and patterns are both given (``hf`` would ignore the
    patterns)."""
    if files and (include or exclude):
        raise ValueError(f"hf download ignores --include/--exclude when file names are given ({repo}: {files})")
    words = ["hf", "download", repo, *files]
    for option, patterns in (("--include", include), ("--exclude", exclude)):
        for pattern in patterns:
            words += [option, pattern]
    return shlex.join(words + ["--local-dir", str(local_dir)])
