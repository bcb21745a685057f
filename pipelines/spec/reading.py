"""Reading a spec file without trusting it: a regular file (never a FIFO or a device, which would block or
stream forever), of bounded size, UTF-8 text without NUL bytes (:func:`read_spec_text`)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from pipelines.errors import SpecError

__all__ = ["MAX_SPEC_BYTES", "read_spec_text"]


#: Largest spec file :func:`~pipelines.spec.model.load_spec` reads, in bytes (the service's default ``max_body_bytes``).
MAX_SPEC_BYTES = 1 << 20


def _file_kind(mode: int) -> str:
    kinds = [(stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
             (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")]
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def read_spec_text(path: str | Path, max_bytes: int = MAX_SPEC_BYTES) -> str:
    """The text of a spec file: a regular file (a FIFO or a device is refused without being read, so neither
    blocks nor streams forever) of at most ``max_bytes`` bytes of UTF-8 text.

    Raises
    ------
    SpecError
        Naming the file and what is wrong with it.
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
        if not stat.S_ISREG(mode):
            raise SpecError(f"cannot read spec {p}: it is {_file_kind(mode)}; give a YAML or JSON file")
        # O_NONBLOCK: should the path have become a FIFO since the stat, opening it does not wait for a writer.
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
        with os.fdopen(fd, "rb") as fh:
            mode = os.fstat(fh.fileno()).st_mode
            if not stat.S_ISREG(mode):
                raise SpecError(f"cannot read spec {p}: it is {_file_kind(mode)}; give a YAML or JSON file")
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise SpecError(f"cannot read spec {p}: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise SpecError(f"spec {p} is larger than {max_bytes:,} bytes, the most a spec file may have")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SpecError(f"spec {p} is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}): a spec is "
                        "YAML or JSON saved as UTF-8") from None
    if "\x00" in text:
        raise SpecError(f"spec {p} contains NUL bytes (offset {text.index(chr(0))}): it is a binary file, not YAML "
                        "or JSON text")
    return text
