"""Outputs written whole or not at all: atomic files, output folders, checks before the work.

``atomic_write(path)`` writes under a temporary name in the file's folder, fsyncs and renames it
into place with ``os.replace`` (a symlink at ``path`` is replaced, its target untouched); an error
or a signal part-way removes the temporary file. An :class:`OutputFolder` stages a command's
files inside its folder; ``commit`` replaces the previous outputs as a whole (those its manifest
lists and the known names) and writes the manifest last, listing the outputs: a folder without
its manifest is incomplete. :class:`Outputs` holds one command's outputs: declaring one checks
that it can be written, before any work starts. Writing errors (a full disk) become one
:class:`~frslam_graph.errors.OutputError` naming the output.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from frslam_graph.errors import Interrupted, OutputError

#: name prefix of temporary files and staging folders (removed at the next commit into the folder)
TEMP_PREFIX = ".frslam-tmp-"
#: figure formats the plots are written in (by the path's extension)
FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def _temp_path(path: Path) -> Path:
    return path.parent / f"{TEMP_PREFIX}{secrets.token_hex(4)}-{path.name}"


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_write(path: str | Path, binary: bool = False) -> Iterator[IO[Any]]:
    """A file object whose content replaces ``path`` whole when the block ends without error."""
    path = Path(path)
    tmp = _temp_path(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)  # umask applies
    try:
        with os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_write(path) as fh:
        fh.write(text)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_write(path, binary=True) as fh:
        fh.write(data)
    return Path(path)


def save_figure(fig: Any, path: str | Path, dpi: float | None = None) -> Path:
    """Write a matplotlib figure atomically, in the format of the path's extension."""
    path = Path(path)
    with atomic_write(path, binary=True) as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".").lower() or "png", dpi=dpi)
    return path


def _error(exc: OSError, path: Path) -> OutputError:
    return OutputError(f"cannot write ({exc.strerror or exc}); nothing written there", source=path)


@contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT / SIGTERM wait until the block is done (then arrive as usual)."""
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _fsync_tree(folder: Path) -> None:
    """fsync every file under ``folder`` (written by code that does not, e.g. a bag writer)."""
    for root, _dirs, files in os.walk(folder):
        for name in files:
            fd = os.open(Path(root) / name, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(Path(root))


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


class OutputFolder:
    """A command's outputs in ``folder``, replacing the previous ones as a whole.

    Use as a context manager: ``write(name, writer)`` stages an output (``writer(path)`` writes a
    file or folder at ``path`` in a staging folder), ``commit(manifest)`` moves every staged
    output into place and the JSON manifest (``manifest`` plus ``outputs``, the list of outputs)
    last; leaving the block without a commit removes what was staged.
    """

    def __init__(
        self,
        folder: str | Path,
        manifest: str,
        known: Iterable[str] = (),
        on_commit: Callable[[Path], object] | None = None,
    ):
        self.folder = Path(folder)
        self.manifest = manifest
        self.known = {*known, manifest}
        self.committed = False
        #: the outputs in place after the commit, the manifest last
        self.outputs: list[Path] = []
        self._on_commit = on_commit
        self._stage: Path | None = None

    def __enter__(self) -> OutputFolder:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._stage = self.folder / f"{TEMP_PREFIX}{secrets.token_hex(4)}"
            self._stage.mkdir()
        except OSError as exc:
            raise _error(exc, self.folder) from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._stage is not None:
            shutil.rmtree(self._stage, ignore_errors=True)
            self._stage = None

    def write(self, name: str, writer: Callable[[Path], object]) -> Path:
        """Stage output ``name`` written by ``writer(path)``; its final path."""
        if self._stage is None:
            raise RuntimeError("OutputFolder.write outside its with-block")
        try:
            writer(self._stage / name)
        except OSError as exc:
            raise _error(exc, self.folder / name) from None
        return self.folder / name

    def previous(self) -> list[str]:
        """Outputs of the previous command in the folder: those its manifest lists, the known names."""
        names = set(self.known)
        try:
            listed = json.loads((self.folder / self.manifest).read_text()).get("outputs", [])
        except (OSError, ValueError, AttributeError):
            listed = []
        names |= {n for n in listed if isinstance(n, str) and n == Path(n).name and n not in ("", ".", "..")}
        stale = {p.name for p in self.folder.glob(f"{TEMP_PREFIX}*") if p != self._stage}
        return sorted(n for n in names | stale if os.path.lexists(self.folder / n))

    def commit(self, manifest: dict[str, Any]) -> list[Path]:
        """Replace the previous outputs by the staged ones, the manifest last; their paths.

        SIGINT / SIGTERM wait until the commit is done; a process killed during it leaves the
        folder without a manifest."""
        assert self._stage is not None, "commit outside the with-block"
        names = sorted(p.name for p in self._stage.iterdir())
        content = {**manifest, "outputs": [*names, self.manifest]}
        self.write(self.manifest, lambda p: write_text(p, json.dumps(content, indent=1)))
        try:
            _fsync_tree(self._stage)
        except OSError as exc:
            raise _error(exc, self.folder) from None
        previous = self.previous()
        with _signals_held():
            try:
                for name in (self.manifest, *previous):  # the manifest first: incomplete from now
                    _remove(self.folder / name)
                for name in [*names, self.manifest]:
                    os.replace(self._stage / name, self.folder / name)
                _fsync_dir(self.folder)
            except OSError as exc:
                raise _error(exc, self.folder) from None
            self.committed = True
            self.outputs = [self.folder / n for n in content["outputs"]]
            if self._on_commit is not None:
                self._on_commit(self.folder)
        return list(self.outputs)


def check_folder(path: str | Path, option: str = "--out", where: str | None = None) -> None:
    """OutputError (naming ``where``, default the option and path) unless ``path`` is a folder
    one can write in, or one that can be created."""
    path = Path(path)
    where = where or f"{option} {path}"
    if path.exists() and not path.is_dir():
        raise OutputError("exists and is not a folder (expected an output folder)", source=where)
    probe = path.absolute()
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{probe} is not a folder, cannot create the output folder in it", source=where)
    tmp = _temp_path(probe / "probe")
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        tmp.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write in {probe} ({exc.strerror or exc})", source=where) from None


def check_file(path: str | Path, suffixes: Iterable[str], option: str = "--out") -> None:
    """OutputError unless ``path`` has one of ``suffixes``, is not a folder and its folder can be written."""
    path = Path(path)
    suffixes = tuple(suffixes)
    where = f"{option} {path}"
    if path.suffix.lower() not in suffixes:
        raise OutputError(
            f"unsupported extension '{path.suffix}' (expected {', '.join(suffixes)})", source=where
        )
    if path.is_dir():
        raise OutputError("is a folder (expected a file to write)", source=where)
    check_folder(path.parent, option, where)


class Outputs:
    """One command's outputs, each checked when declared (before the work starts).

    Use around the command's work: an :class:`~frslam_graph.errors.Interrupted` leaving the
    block carries the outputs complete by then (``outputs``).
    """

    def __init__(self) -> None:
        self.done: list[Path] = []
        self._folders: dict[Path, OutputFolder] = {}

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, typ: object, exc: BaseException | None, tb: object) -> None:
        if isinstance(exc, Interrupted):
            exc.outputs = [str(p) for p in self.done]

    def folder(
        self, path: str | Path, manifest: str, known: Iterable[str] = (), option: str = "--out"
    ) -> OutputFolder:
        """An output folder (checked now) whose outputs replace the previous ones on commit."""
        check_folder(path, option)
        folder = OutputFolder(path, manifest, known, on_commit=self.done.append)
        self._folders[folder.folder] = folder
        return folder

    def files(self) -> list[Path]:
        """Every file (or folder, e.g. a bag) written so far, in the order written: an output
        folder's outputs as its manifest lists them."""
        out: list[Path] = []
        for path in self.done:
            folder = self._folders.get(path)
            out.extend(folder.outputs if folder is not None and folder.committed else [path])
        return out

    def file(self, path: str | Path, suffixes: Iterable[str], option: str = "--out") -> Path:
        """An output file (checked now: extension, not a folder, folder writable)."""
        check_file(path, suffixes, option)
        return Path(path)

    def write(self, path: Path, writer: Callable[[Path], object]) -> Path:
        """Write one output file with ``writer(path)`` (which writes atomically); errors name it."""
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            writer(path)
        except OSError as exc:
            raise _error(exc, path) from None
        self.done.append(path)
        return path
