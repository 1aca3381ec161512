"""The public local-map datasets: what they are, where they live, their checksums, and fetching them.

Two distributions hold them. I-SLSJF (OpenSLAM, ``github.com/OpenSLAM-org/openslam_2d-i-slsjf``)
ships MATLAB local maps (``localmap_<k>.mat``) with raw data and, for the simulations,
ground truth. Linear SLAM ships the same kind of maps as text (``localmap_<k>.txt``); its
code is distributed through OpenSLAM; the copy on GitHub used here is
``github.com/MDavid599/MicroMouseSLAM`` (``LinearSLAMCode/``), whose 8240 files match the
reference copy (two compared: same sizes, same text). Both are pinned to a commit, so the
files cannot change under the checksums.

``datasets.sha256`` (beside this module, ``sha256sum`` format, paths relative to the cache
root) records the SHA-256 of every file of every set present in the reference copy
(``../shared/data`` beside the project); sets not present there (e.g. DLR 3298) have none,
are fetched unverified, and say so. A cache folder has the reference copy's layout,
``<cache>/<folder>/<file>``, so a cache (or the reference copy) can serve as a ``source``
mirror for another machine.

Fetching downloads into a temporary folder beside the target and renames it into place
once every file has arrived and matched its checksum, so the cache never holds a partial
set, nor a file whose checksum is known and differs.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import secrets
import shutil
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

from .errors import MapjoinError, shown_name

__all__ = ["DATASETS", "Dataset", "FetchError", "Fetched", "checksums", "default_cache", "fetch", "get",
           "is_cached"]

_ISLSJF = "https://raw.githubusercontent.com/OpenSLAM-org/openslam_2d-i-slsjf/ffccc82fc0f6a4ca4aa1ccbabb1834bcdf7026f9"
_LINEARSLAM = ("https://raw.githubusercontent.com/MDavid599/MicroMouseSLAM/fa5cd2ec8766b65f820ab24705f9c44e0db1a9d0"
               "/LinearSLAMCode/LinearSLAM_C/DatasetsForC/DatasetsForC")
_SIMULATION = ("sensor_data.mat", "store_robotOdo.mat", "store_robotTrue.mat", "store_speed.mat",
               "store_speedTrue.mat", "store_turnrate.mat", "store_turnrateTrue.mat")
_WORKERS = 8  # parallel downloads: thousands of small files
_TIMEOUT = 60.0  # seconds without data before a download fails


class FetchError(MapjoinError):
    """A dataset that could not be fetched: unreachable source, missing file, or wrong checksum.

    ``argument`` names the :func:`fetch` argument whose change is the remedy (``into`` or
    ``source``), so that a caller can say how to pass it; ``None`` when no argument helps.
    """

    def __init__(self, message: str, argument: str | None = None) -> None:
        super().__init__(message)
        self.argument = argument


@dataclass(frozen=True)
class Dataset:
    """One set of local maps: its files are ``localmap_1..maps.<extension>``, ``extras`` and ``optional``.

    ``optional`` files are in the reference copy but not confirmed at the default source;
    when a source lacks one it is skipped with a note instead of failing the fetch.
    """

    name: str
    folder: str
    description: str
    distribution: str
    url: str
    maps: int
    extension: str
    extras: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()

    @property
    def files(self) -> list[str]:
        """Every file of the set, local maps first (in map order)."""
        maps = [f"localmap_{k}.{self.extension}" for k in range(1, self.maps + 1)]
        return [*maps, *self.extras, *self.optional]


def _islsjf(name: str, folder: str, description: str, maps: int, extras: tuple[str, ...] = (),
            optional: tuple[str, ...] = ()) -> Dataset:
    return Dataset(name, folder, description, "I-SLSJF", f"{_ISLSJF}/{folder}", maps, "mat", extras, optional)


def _linearslam(name: str, folder: str, description: str, maps: int) -> Dataset:
    return Dataset(name, f"linearslam_txt/{folder}", description, "Linear SLAM", f"{_LINEARSLAM}/{folder}", maps,
                   "txt")


DATASETS: dict[str, Dataset] = {dataset.name: dataset for dataset in [
    _islsjf("vicpark-200", "VicPark_200_local_maps", "Victoria Park, 200 local maps (the paper's Section 7), "
            "with the preprocessed raw data", 200,
            ("VicPark_clean_data.mat", "data_sensor_clean_clean.mat", "ControlData.mat", "readme.txt")),
    _islsjf("vicpark-6898", "VicPark_6898_local_maps", "Victoria Park, 6898 small local maps", 6898,
            optional=("VicPark_clean_data.mat", "data_sensor_clean_clean.mat")),
    _islsjf("dlr-200", "DLR_200_local_maps", "DLR Spatial Cognition (indoor), 200 local maps, with raw data", 200,
            ("corrected_data_circles.mat",), ("map.circles",)),
    _islsjf("dlr-3298", "DLR_3298_local_maps", "DLR Spatial Cognition (indoor), 3298 small local maps", 3298),
    _islsjf("sim-535", "535_data_5_local_maps", "simulation, 535 steps, 5 local maps, with ground truth", 5,
            ("parameters.txt", *_SIMULATION), ("store_beaconsTrue.mat",)),
    _islsjf("sim-8240", "8240_data_50_local_maps", "simulation, 8240 steps, 50 local maps, with ground truth", 50,
            ("store_beaconsTrue.mat", *_SIMULATION), ("parameters.txt",)),
    _islsjf("sim-35188", "35188_data_700_local_maps", "simulation, 35188 steps, 700 local maps, with ground truth",
            700, ("parameters.txt", "sensor_data.mat", "store_beaconsTrue.mat", "store_robotTrue.mat")),
    _linearslam("linearslam-8240", "8240_data_50_local_maps", "simulation 8240, 50 local maps (Linear SLAM text)", 50),
    _linearslam("linearslam-vicpark-6898", "VicPark_6898_local_maps",
                "Victoria Park, 6898 local maps (Linear SLAM text)", 6898),
    _linearslam("linearslam-dlr-3298", "DLR_3298_local_maps", "DLR, 3298 local maps (Linear SLAM text)", 3298),
    _linearslam("linearslam-35188", "35188_data_700_local_maps", "simulation 35188, 700 local maps (Linear SLAM text)",
                700),
]}


@dataclass(frozen=True)
class Fetched:
    """What :func:`fetch` did: the folder, how many files and bytes arrived, whether they were verified."""

    dataset: Dataset
    path: Path
    files: int
    size: int
    verified: bool
    skipped: tuple[str, ...] = ()
    already_cached: bool = False


def get(name: str) -> Dataset:
    """The dataset called ``name``; a FetchError lists the known names otherwise."""
    if name not in DATASETS:
        raise FetchError(f"unknown dataset {name!r}; expected one of {', '.join(DATASETS)} (mapjoin datasets list)")
    return DATASETS[name]


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/mapjoin`` (when that is an absolute path), else ``~/.cache/mapjoin``."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    return (Path(base) if os.path.isabs(base) else Path.home() / ".cache") / "mapjoin"


@cache
def _recorded() -> dict[str, str]:
    """Recorded SHA-256 per path (``folder/file``) from ``datasets.sha256``."""
    text = resources.files(__package__).joinpath("datasets.sha256").read_text(encoding="ascii")
    return {path: digest for digest, path in (line.split("  ", 1) for line in text.splitlines())}


def checksums(dataset: Dataset) -> dict[str, str] | None:
    """The recorded SHA-256 of each file of ``dataset``, or None when none is known (it cannot be verified)."""
    recorded = _recorded()
    known = {file: recorded[f"{dataset.folder}/{file}"] for file in dataset.files
             if f"{dataset.folder}/{file}" in recorded}
    return known or None


def is_cached(dataset: Dataset, into: Path | None = None) -> bool:
    """Whether every required file of ``dataset`` is in the cache (sizes and checksums are not read)."""
    folder = (into or default_cache()) / dataset.folder
    return all((folder / file).is_file() for file in dataset.files if file not in dataset.optional)


def fetch(name: str, into: str | Path | None = None, source: str | None = None,
          progress: Callable[[int], None] | None = None) -> Fetched:
    """Download dataset ``name`` into ``into`` (default :func:`default_cache`) and verify every checksum.

    ``source`` replaces the default source: a URL or local folder laid out like the cache
    (``<source>/<folder>/<file>``), e.g. ``https://mirror.example/data`` or ``../shared/data``. A set already complete
    in the cache is not downloaded again when its files match their checksums (or none are
    known). ``progress`` is called with the number of files done so far.
    """
    dataset = get(name)
    root = Path(into) if into is not None else default_cache()
    target = root / dataset.folder
    expected = checksums(dataset)
    if is_cached(dataset, root) and (expected is None or _matches(target, expected)):
        present = [file for file in dataset.files if (target / file).is_file()]
        return Fetched(dataset, target, len(present), sum((target / file).stat().st_size for file in present),
                       expected is not None, already_cached=True)
    base = dataset.url if source is None else f"{_as_url(source).rstrip('/')}/{dataset.folder}"
    created = [folder for folder in (target.parent, *target.parent.parents) if not folder.exists()]
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part")
        temporary.mkdir()
    except OSError as error:
        _remove_empty(created)
        raise FetchError(f"{shown_name(str(root))}: cannot create the cache folder ({error.strerror or error}); "
                         "choose another cache folder", argument="into") from None
    done = False
    try:
        downloads = _download_all(dataset, base, temporary, progress)
        if expected is not None:
            _verify(downloads, expected, base, target)
        _replace(temporary, target)
        done = True
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
        if not done:  # a failed fetch leaves no trace: not even the cache folders it made
            _remove_empty(created)
    arrived = {file: size for file, (_, size) in downloads.items() if size is not None}
    skipped = tuple(file for file, (_, size) in downloads.items() if size is None)
    return Fetched(dataset, target, len(arrived), sum(arrived.values()), expected is not None, skipped)


def _remove_empty(folders: list[Path]) -> None:
    """Remove ``folders`` (innermost first, as listed) that are empty: those a failed fetch made."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _as_url(source: str) -> str:
    """``source`` as a URL: URLs as they are, local paths as ``file://`` URLs; an empty ``source`` is refused
    (it would name the current folder)."""
    if not source.strip():
        raise FetchError("the source is empty; expected a URL or a folder")
    if "://" in source:
        return source
    return Path(source).expanduser().resolve().as_uri()


def _download_all(dataset: Dataset, base: str, folder: Path,
                  progress: Callable[[int], None] | None) -> dict[str, tuple[str | None, int | None]]:
    """(SHA-256, size) of each file downloaded into ``folder``; (None, None) for absent optional files."""
    def one(file: str) -> tuple[str | None, int | None]:
        return _download(f"{base}/{urllib.parse.quote(file)}", folder / file, file in dataset.optional, dataset)

    results = {}
    with ThreadPoolExecutor(_WORKERS) as pool:
        futures = [pool.submit(one, file) for file in dataset.files]
        try:
            for count, (file, future) in enumerate(zip(dataset.files, futures), 1):
                results[file] = future.result()
                if progress:
                    progress(count)
        except BaseException:
            pool.shutdown(cancel_futures=True)  # the first failure ends the fetch: start no more downloads
            raise
    return results


def _download(url: str, path: Path, optional: bool, dataset: Dataset) -> tuple[str | None, int | None]:
    """Copy ``url`` to ``path``, hashing on the way; (None, None) if an optional file is absent."""
    digest, size = hashlib.sha256(), 0
    try:
        with urllib.request.urlopen(url, timeout=_TIMEOUT) as response, open(path, "xb") as file:
            while chunk := response.read(1 << 16):
                digest.update(chunk)
                file.write(chunk)
                size += len(chunk)
    except (urllib.error.URLError, http.client.HTTPException, TimeoutError, ConnectionError) as error:
        if _not_found(error):
            if optional:
                return None, None
            raise FetchError(f"{shown_name(url)}: not found; the source does not hold {dataset.name} in the "
                             "expected layout "
                             f"(<source>/{dataset.folder}/<file>)") from None
        reason = getattr(error, "reason", None) or error
        raise FetchError(f"cannot download {shown_name(url)} ({shown_name(str(reason))}); check the network "
                         f"connection, or fetch from a mirror or a local copy (a URL or folder holding "
                         f"{dataset.folder}/)", argument="source") from None
    return digest.hexdigest(), size


def _not_found(error: Exception) -> bool:
    """Whether a download failed because the file is not there (HTTP 404 or a missing local file)."""
    if isinstance(error, urllib.error.HTTPError):
        return error.code == 404
    return isinstance(getattr(error, "reason", error), FileNotFoundError)


def _verify(downloads: dict[str, tuple[str | None, int | None]], expected: dict[str, str], base: str,
            target: Path) -> None:
    """Every downloaded file's SHA-256 against the record; a FetchError names the first that differs."""
    for file, (digest, _) in downloads.items():
        if digest is not None and digest != expected[file]:
            raise FetchError(f"{shown_name(f'{base}/{file}')}: SHA-256 {digest} differs from the recorded {expected[file]}; the "
                             f"file is corrupt or not the published one, so nothing was written to {target}")


def _matches(folder: Path, expected: dict[str, str]) -> bool:
    """Whether every file present in ``folder`` has its recorded SHA-256."""
    return all(_sha256(folder / file) == digest for file, digest in expected.items() if (folder / file).is_file())


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _replace(temporary: Path, target: Path) -> None:
    """Move the downloaded folder into place; an older copy at ``target`` is removed only after the move."""
    if not target.exists():
        temporary.rename(target)
        return
    old = target.with_name(f".{target.name}.{secrets.token_hex(4)}.old")
    target.rename(old)
    temporary.rename(target)
    shutil.rmtree(old, ignore_errors=True)
