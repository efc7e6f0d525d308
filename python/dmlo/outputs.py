"""Output folders and files of the commands: one run's files at a time, and one-line errors when they
cannot be written.

- :func:`prepare_output_folder` creates a run folder, or refuses one that holds an earlier run's files
  unless asked to overwrite them, and then deletes exactly those files first: two runs' files never lie
  side by side (a ``metrics.json`` of one run beside the poses of another).
- :class:`FrameFiles` appends each frame's lines to several files (poses in KITTI and TUM, diagnostics)
  so that they always hold the same frames, whatever stops the run: a full disk, Ctrl-C.
- :func:`atomic_output` writes a whole file under a temporary name and renames it: a failure leaves the
  previous file or none, never half of one.

Every failure to write is an :class:`OutputError` whose message names the path and the reason on one line.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType

__all__ = [
    "BENCH_FILES",
    "RUN_FILES",
    "FrameFiles",
    "OutputError",
    "atomic_output",
    "check_output_folder",
    "describe_os_error",
    "make_folder",
    "prepare_output_folder",
]

# What `dmlo run` (`run_sequence`) writes into its folder.
RUN_FILES = (
    "config.json",
    "poses_kitti.txt",
    "poses_tum.txt",
    "diagnostics.jsonl",
    "ground_truth_kitti.txt",
    "metrics.json",
    "trajectory.png",
)
# What `dmlo bench` (`benchmark_sequence`) writes: the ground truth and one pose file per method, named
# after the method: DMLO's rows all start with "DMLO", the peers' (`dmlo.peers.peers.PEERS`, a test keeps
# them covered) with the library's name.
BENCH_FILES = ("ground_truth.txt", "DMLO*.txt", "KISS-ICP*.txt", "small_gicp*.txt", "Open3D*.txt")


class OutputError(OSError):
    """An output that cannot be written, or a folder that holds another run's files: one line that names
    the path."""


def describe_os_error(err: OSError) -> str:
    """The reason of an `OSError` in words, without its errno number and repeated path."""
    if err.strerror:
        return err.strerror[0].lower() + err.strerror[1:]
    return str(err) or type(err).__name__


def _leftovers(name: str) -> str:
    """The temporary files of an interrupted atomic write of `name` (this module's and `dmlo.poses`')."""
    return f".{name}.*.tmp*"


def _owned(folder: Path, patterns: Iterable[str]) -> list[Path]:
    wanted = [p for pattern in patterns for p in (pattern, _leftovers(pattern))]
    return sorted(entry for entry in folder.iterdir() if any(fnmatch.fnmatchcase(entry.name, p) for p in wanted))


def _not_a_folder(path: Path) -> Path | None:
    """The first of `path` and its parents that exists and is not a folder (a file in the way), if any."""
    for candidate in (path, *path.parents):
        if candidate.exists() or candidate.is_symlink():
            return None if candidate.is_dir() else candidate
    return None


def make_folder(path: Path, what: str = "output folder") -> None:
    """`mkdir -p`, or an `OutputError` that says which file stands in the way."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        blocking = _not_a_folder(path)
        if blocking is not None:
            reason = f"{blocking} is a file, not a folder"
        else:
            reason = describe_os_error(err)
        raise OutputError(f"cannot create the {what} {path}: {reason}") from None


def check_output_folder(
    folder: str | os.PathLike[str],
    owned: Sequence[str],
    *,
    overwrite: bool = False,
    also_refuse: Sequence[str] = (),
) -> list[Path]:
    """What :func:`prepare_output_folder` checks, changing nothing (for a command to refuse a folder before
    its slow start): raises its `OutputError`s, or returns the earlier run's files it would delete."""
    folder = Path(folder)
    blocking = _not_a_folder(folder)
    if blocking is not None:
        where = "is a file" if blocking == folder else f"is under {blocking}, a file"
        raise OutputError(f"output folder {folder} {where}, not a folder")
    if not folder.is_dir():
        return []
    try:
        earlier = _owned(folder, [*owned, *also_refuse])
    except OSError as err:
        raise OutputError(f"cannot read the output folder {folder}: {describe_os_error(err)}") from None
    for path in earlier:
        if path.is_dir() and not path.is_symlink():
            raise OutputError(f"{path} is a folder where the run writes a file; remove it or choose another output folder")
    if earlier and not overwrite:
        names = ", ".join(path.name for path in earlier[:4]) + (", …" if len(earlier) > 4 else "")
        raise OutputError(
            f"{folder} holds the files of an earlier run ({names}); pass --overwrite (overwrite=True) to "
            "replace them, or choose another output folder"
        )
    return earlier


def prepare_output_folder(
    folder: str | os.PathLike[str],
    owned: Sequence[str],
    *,
    overwrite: bool = False,
    also_refuse: Sequence[str] = (),
) -> Path:
    """Makes `folder` ready for a new run that writes the files `owned` (names, or `fnmatch` patterns).

    The folder is created when missing. When it holds files of an earlier run (`owned` or `also_refuse`:
    what another kind of run writes into its folder) it is refused with an `OutputError`, unless
    `overwrite`: then exactly those files are deleted first, and the folder's other files are left alone.
    A folder in place of one of those files is refused either way (nothing is deleted recursively).
    """
    folder = Path(folder)
    earlier = check_output_folder(folder, owned, overwrite=overwrite, also_refuse=also_refuse)
    make_folder(folder)
    for path in earlier:
        try:
            path.unlink(missing_ok=True)
        except OSError as err:
            raise OutputError(f"cannot delete {path} of the earlier run: {describe_os_error(err)}") from None
    return folder


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yields a temporary path beside `path` to write the whole file to; renames it over `path` when the
    block ends without an error, deletes it otherwise. OS errors become an `OutputError` naming `path`."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"cannot write {path}: it is a folder")
    try:
        descriptor, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as err:
        raise OutputError(f"cannot write {path}: {describe_os_error(err)}") from None
    os.close(descriptor)
    temporary = Path(name)
    try:
        yield temporary
        os.replace(temporary, path)
    except OSError as err:
        temporary.unlink(missing_ok=True)
        if isinstance(err, OutputError):
            raise
        raise OutputError(f"cannot write {path}: {describe_os_error(err)}") from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def _write_all(descriptor: int, data: bytes) -> None:
    """`os.write` until all of `data` is written (a write may take only part of it, e.g. on a full disk)."""
    view = memoryview(data)
    while view:
        written = os.write(descriptor, view)
        if written == 0:  # not expected from a regular file; never loop forever on it
            raise OSError(errno.EIO, "the file took no bytes")
        view = view[written:]


class FrameFiles:
    """Appends one frame's lines to every one of several files, or to none of them.

    A run writes each frame's pose to the KITTI and TUM files and its diagnostics to a third as it goes,
    so that a run cut short keeps every frame it finished. If a write fails (a full disk: `OSError`) or
    the run is stopped in the middle of a frame (Ctrl-C between two of the files), every file is
    truncated back to the end of the last complete frame, so they always hold the same frames.

    Why truncation rather than write-then-rename: renaming after every frame would rewrite the whole
    files each frame (quadratic in the length of a drive), and renaming after a batch of frames would lose
    the batch's finished frames on Ctrl-C. Appending with unbuffered writes and cutting back to a known
    length on failure keeps every finished frame at the cost of one `ftruncate` per file, only on failure.
    """

    def __init__(self, paths: Sequence[str | os.PathLike[str]]) -> None:
        self.paths = [Path(path) for path in paths]
        self.frames = 0
        self._descriptors: list[int] = []
        self._lengths: list[int] = []
        try:
            for path in self.paths:
                if path.is_dir():
                    raise OutputError(f"cannot write {path}: it is a folder")
                try:
                    self._descriptors.append(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666))
                except OSError as err:
                    raise OutputError(f"cannot write {path}: {describe_os_error(err)}") from None
                self._lengths.append(0)
        except BaseException:
            self._close_all()
            raise

    def append(self, lines: Sequence[str]) -> None:
        """Writes `lines[i]` (one frame's whole text, newline included) to file `i`, all or none."""
        if len(lines) != len(self.paths):
            raise ValueError(f"expected {len(self.paths)} texts, one a file, got {len(lines)}")
        chunks = [line.encode("utf-8") for line in lines]
        index = 0
        try:
            for index, (descriptor, chunk) in enumerate(zip(self._descriptors, chunks, strict=True)):
                _write_all(descriptor, chunk)
        except BaseException as err:
            self._roll_back()
            if isinstance(err, OSError) and not isinstance(err, OutputError):
                raise OutputError(
                    f"cannot write {self.paths[index]}: {describe_os_error(err)} (the output files hold the "
                    f"{self.frames} frames finished before)"
                ) from None
            raise
        self._lengths = [length + len(chunk) for length, chunk in zip(self._lengths, chunks, strict=True)]
        self.frames += 1

    def _roll_back(self) -> None:
        """Cuts every file back to the end of the last complete frame (best effort: a file that cannot
        be cut is left as it is rather than hiding the error that brought us here)."""
        for descriptor, length in zip(self._descriptors, self._lengths, strict=True):
            with contextlib.suppress(OSError):
                os.ftruncate(descriptor, length)
                os.lseek(descriptor, length, os.SEEK_SET)

    def _close_all(self) -> OSError | None:
        first: OSError | None = None
        for descriptor in self._descriptors:
            try:
                os.fsync(descriptor)
            except OSError as err:
                first = first or err
            try:
                os.close(descriptor)
            except OSError as err:
                first = first or err
        self._descriptors = []
        return first

    def close(self) -> None:
        error = self._close_all()
        if error is not None:
            raise OutputError(f"cannot finish writing {self.paths[0].parent}: {describe_os_error(error)}")

    def __enter__(self) -> FrameFiles:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:  # the error on its way out says more than a second one from closing
            self._close_all()
