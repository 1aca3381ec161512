"""The dataset catalogue and `mapjoin datasets`: checksums of the reference copy, fetching from file:// mirrors."""

from __future__ import annotations

import dataclasses
import filecmp
import hashlib
import os
import shutil
import urllib.error
from pathlib import Path

import pytest
from cli_runner import run

from mapjoin import datasets
from mapjoin.datasets import DATASETS, FetchError


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def mirror_of(data_dir: Path, tmp_path: Path, *names: str) -> Path:
    """A copy of the reference copy's folders of ``names`` (to corrupt or thin out), laid out like the cache."""
    mirror = tmp_path / "mirror"
    for name in names:
        shutil.copytree(data_dir / DATASETS[name].folder, mirror / DATASETS[name].folder)
    return mirror


def leftovers(folder: Path) -> list[str]:
    """Temporary files or folders a fetch left behind."""
    return [path.name for path in folder.rglob(".*")]


# ---------------------------------------------------------------------------------------
# The catalogue and its checksums


def test_recorded_checksums_are_those_of_every_file_of_the_reference_copy(data_dir):
    checked = 0
    for dataset in DATASETS.values():
        folder = data_dir / dataset.folder
        recorded = datasets.checksums(dataset)
        if not folder.is_dir():
            assert recorded is None, dataset.name
            continue
        assert sorted(os.listdir(folder)) == sorted(dataset.files), dataset.name
        assert recorded == {file: sha256(folder / file) for file in dataset.files}, dataset.name
        checked += len(recorded)
    assert checked == 7429


def test_the_checksum_file_holds_nothing_else():
    recorded = datasets._recorded()
    known = {f"{dataset.folder}/{file}" for dataset in DATASETS.values() if datasets.checksums(dataset)
             for file in dataset.files}
    assert set(recorded) == known
    assert all(len(digest) == 64 and set(digest) <= set("0123456789abcdef") for digest in recorded.values())


def test_sets_absent_from_the_reference_copy_say_they_cannot_be_verified():
    result = run("datasets", "list")
    assert result.exit_code == 0, result.output
    lines = {line.split()[0]: line for line in result.stdout.splitlines()[1:]}
    assert set(lines) == set(DATASETS)
    unverified = {name for name, line in lines.items() if "none known: cannot verify" in line}
    assert unverified == {"dlr-3298", "sim-35188", "linearslam-vicpark-6898", "linearslam-dlr-3298",
                          "linearslam-35188"}
    assert all("SHA-256 of every file" in lines[name] for name in set(DATASETS) - unverified)


def test_default_sources_are_pinned_commits_on_github():
    for dataset in DATASETS.values():
        assert dataset.url.startswith("https://raw.githubusercontent.com/"), dataset.name
        commit = dataset.url.split("/")[5]
        assert len(commit) == 40 and set(commit) <= set("0123456789abcdef"), dataset.name
        assert dataset.url.endswith("/" + dataset.folder.removeprefix("linearslam_txt/")), dataset.name


def test_default_cache_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert datasets.default_cache() == tmp_path / "xdg" / "mapjoin"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the XDG spec: only absolute paths count
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert datasets.default_cache() == tmp_path / "home" / ".cache" / "mapjoin"


# ---------------------------------------------------------------------------------------
# Fetching from a file:// source


def test_fetch_from_the_reference_copy_end_to_end(data_dir, tmp_path):
    cache = tmp_path / "cache"
    result = run("datasets", "fetch", "sim-535", "linearslam-8240", "--into", str(cache),
                 "--source", data_dir.as_uri())
    assert result.exit_code == 0, result.output
    paths = result.stdout.split()
    assert paths == [str(cache / "535_data_5_local_maps"), str(cache / "linearslam_txt" / "8240_data_50_local_maps")]
    assert "sim-535: fetched 14 files, 0.1 MB, every SHA-256 verified" in result.stderr
    assert "linearslam-8240: fetched 50 files, 2.6 MB, every SHA-256 verified" in result.stderr
    for name, path in zip(("sim-535", "linearslam-8240"), paths):
        files = DATASETS[name].files
        assert sorted(os.listdir(path)) == sorted(files)
        assert filecmp.cmpfiles(data_dir / DATASETS[name].folder, path, files, shallow=False)[0] == files
    assert leftovers(cache) == []
    joined = run("join", paths[1], "-o", str(tmp_path / "sim.csv"))
    assert joined.exit_code == 0 and "joined 50 maps" in joined.stderr
    listed = run("datasets", "list", "--into", str(cache))
    header, *rows = listed.stdout.splitlines()
    cached = {row.split()[0]: row[header.index("CACHED"):].split()[0] for row in rows}
    assert cached["sim-535"] == cached["linearslam-8240"] == "yes" and cached["vicpark-200"] == "no"


def test_a_verified_cached_set_is_not_fetched_again(data_dir, tmp_path):
    first = datasets.fetch("sim-535", tmp_path, data_dir.as_uri())
    assert (first.files, first.verified, first.already_cached) == (14, True, False)
    again = datasets.fetch("sim-535", tmp_path, str(tmp_path / "no-such-mirror"))  # no download is attempted
    assert (again.files, again.verified, again.already_cached) == (14, True, True)


def test_a_corrupt_cached_set_is_replaced_whole(data_dir, tmp_path):
    datasets.fetch("sim-535", tmp_path, str(data_dir))  # a plain folder works as a source too
    folder = tmp_path / DATASETS["sim-535"].folder
    (folder / "localmap_2.mat").write_bytes(b"garbage")
    (folder / "stray.txt").write_text("left by someone")
    result = datasets.fetch("sim-535", tmp_path, data_dir.as_uri())
    assert not result.already_cached and result.verified
    assert sha256(folder / "localmap_2.mat") == sha256(data_dir / DATASETS["sim-535"].folder / "localmap_2.mat")
    assert not (folder / "stray.txt").exists() and leftovers(tmp_path) == []


def test_a_file_with_the_wrong_checksum_fails_the_fetch_and_writes_nothing(data_dir, tmp_path):
    mirror = mirror_of(data_dir, tmp_path, "sim-535")
    bad = mirror / "535_data_5_local_maps" / "localmap_3.mat"
    bad.write_bytes(bad.read_bytes()[:-1] + b"\0")
    cache = tmp_path / "cache"
    result = run("datasets", "fetch", "sim-535", "--into", str(cache), "--source", mirror.as_uri())
    assert result.exit_code == 1
    assert result.stderr.startswith(f"Error: {mirror.as_uri()}/535_data_5_local_maps/localmap_3.mat: SHA-256 "
                                    f"{sha256(bad)} differs from the recorded ")
    assert "nothing was written to" in result.stderr and result.stderr.count("\n") == 1
    assert not (cache / "535_data_5_local_maps").exists() and leftovers(cache) == []


def test_a_missing_file_fails_the_fetch_unless_it_is_optional(data_dir, tmp_path):
    mirror = mirror_of(data_dir, tmp_path, "sim-535")
    (mirror / "535_data_5_local_maps" / "store_beaconsTrue.mat").unlink()  # optional: not confirmed on GitHub
    result = run("datasets", "fetch", "sim-535", "--into", str(tmp_path / "cache"), "--source", mirror.as_uri())
    assert result.exit_code == 0, result.output
    assert "sim-535: the source does not hold store_beaconsTrue.mat (optional; skipped)" in result.stderr
    assert "fetched 13 files" in result.stderr
    (mirror / "535_data_5_local_maps" / "localmap_4.mat").unlink()
    result = run("datasets", "fetch", "sim-535", "--into", str(tmp_path / "other"), "--source", mirror.as_uri())
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {mirror.as_uri()}/535_data_5_local_maps/localmap_4.mat: not found; the source "
                             "does not hold sim-535 in the expected layout (<source>/535_data_5_local_maps/<file>)\n")
    assert not (tmp_path / "other" / "535_data_5_local_maps").exists() and leftovers(tmp_path / "other") == []


def test_a_set_without_checksums_is_fetched_and_said_to_be_unverified(data_dir, tmp_path, monkeypatch):
    unverified = dataclasses.replace(DATASETS["sim-535"], name="unverified-535", folder="unverified/sim")
    monkeypatch.setitem(DATASETS, unverified.name, unverified)
    mirror = tmp_path / "mirror"
    shutil.copytree(data_dir / "535_data_5_local_maps", mirror / "unverified" / "sim")
    assert datasets.checksums(unverified) is None
    result = run("datasets", "fetch", "unverified-535", "--into", str(tmp_path / "cache"), "--source", str(mirror))
    assert result.exit_code == 0, result.output
    assert ("unverified-535: fetched 14 files, 0.1 MB, NOT verified: no checksums are known for this set"
            in result.stderr)


def test_progress_is_reported_per_file(data_dir, tmp_path):
    counts: list[int] = []
    datasets.fetch("sim-535", tmp_path, data_dir.as_uri(), progress=counts.append)
    assert counts == list(range(1, 15))


# ---------------------------------------------------------------------------------------
# Failures


def test_network_failure_names_the_url_and_suggests_a_mirror(tmp_path, monkeypatch):
    def offline(url, timeout):
        raise urllib.error.URLError(OSError(-3, "Temporary failure in name resolution"))

    monkeypatch.setattr("urllib.request.urlopen", offline)
    result = run("datasets", "fetch", "dlr-200", "--into", str(tmp_path))
    assert result.exit_code == 1
    url = f"{DATASETS['dlr-200'].url}/localmap_1.mat"
    assert result.stderr.startswith(f"Error: cannot download {url} ([Errno -3] Temporary failure in name resolution); "
                                    "check the network connection, or fetch from a mirror or a local copy (a URL or "
                                    "folder holding DLR_200_local_maps/): pass it with --source URL")
    assert result.stderr.count("\n") == 1 and leftovers(tmp_path) == []
    assert not (tmp_path / "DLR_200_local_maps").exists()


def test_unknown_names_list_the_known_ones():
    result = run("datasets", "fetch", "vicpark-100")
    assert result.exit_code == 1
    assert result.stderr.startswith("Error: unknown dataset 'vicpark-100'; expected one of vicpark-200, vicpark-6898")
    with pytest.raises(FetchError, match="unknown dataset"):
        datasets.fetch("nope")


def test_an_unwritable_cache_is_a_clear_error(tmp_path, data_dir):
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    with pytest.raises(FetchError, match=f"{blocked}: cannot create the cache folder"):
        datasets.fetch("sim-535", blocked, data_dir.as_uri())
    with pytest.raises(FetchError) as raised:
        datasets.fetch("sim-535", blocked, data_dir.as_uri())
    assert raised.value.argument == "into" and "--" not in str(raised.value)  # the library names no option
    result = run("datasets", "fetch", "sim-535", "--into", str(blocked / "cache"), "--source", data_dir.as_uri())
    assert result.exit_code == 1 and result.stderr.count("\n") == 1
    assert result.stderr.rstrip().endswith("choose another cache folder: pass it with --into DIR")


@pytest.mark.parametrize("source", ["", " "])
def test_an_empty_source_is_refused_not_read_as_the_current_folder(tmp_path, source):
    result = run("datasets", "fetch", "sim-535", "--into", str(tmp_path / "cache"), "--source", source)
    assert result.exit_code == 2 and "Invalid value for '--source': is empty" in result.stderr
    assert not (tmp_path / "cache").exists()
    with pytest.raises(FetchError, match="the source is empty"):
        datasets.fetch("sim-535", tmp_path / "cache", source)
    assert not (tmp_path / "cache").exists()
