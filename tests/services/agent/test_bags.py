"""Which MCAP files in the watched folders are closed (and so uploaded), and to which run: a rosbag2
folder's files once its metadata.yaml lists them or a later split exists, each only with MCAP's
trailing magic written; any file once it has not changed for the idle time (an injected clock, no
sleeping); names the agent leaves alone; run ids the depot takes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from core.ids import ID_LENGTH, check_id
from services.agent import bags as bags_module
from services.agent.bags import (
    MCAP,
    ROSBAG2,
    Bag,
    BagScanner,
    Scan,
    Stamp,
    is_bag_name,
    metadata_files,
    run_id_for,
    split_of,
)
from tests.services.agent.mcap_files import write_bag, write_mcap, write_metadata

IDLE_S = 30.0


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def scanner(clock: Clock) -> BagScanner:
    return BagScanner(IDLE_S, clock=clock)


@pytest.fixture
def root(tmp_path: Path) -> Path:
    watched = tmp_path / "watched"
    watched.mkdir()
    return watched


def real(path: Path) -> str:
    return os.path.realpath(path)


def closed(scan: Scan) -> dict[str, Bag]:
    return {bag.path: bag for bag in scan.closed}


def append(path: Path, data: bytes = b"more") -> None:
    with open(path, "ab") as fh:
        fh.write(data)


# --- rosbag2 folders ------------------------------------------------------------------------------


def test_a_closed_bag_listed_in_its_metadata_is_closed_at_once(scanner: BagScanner, root: Path):
    files = write_bag(root / "rosbag2_2024_01_31-12_00_00", splits=2)
    scan = scanner.scan([root], {})
    bags = closed(scan)
    assert sorted(bags) == sorted(real(f) for f in files)
    for bag in bags.values():
        assert (bag.run_id, bag.application, bag.why) == ("rosbag2_2024_01_31-12_00_00", ROSBAG2, "metadata.yaml")
        assert bag.is_mcap and bag.stamp == Stamp.of(os.stat(bag.path))
    assert [b.path for b in scan.closed] == [real(f) for f in files]  # oldest first: splits in order
    assert sorted(scan.pending) == sorted(bags) and scan.found == set(bags)


def test_metadata_listing_a_file_without_its_footer_waits_for_idleness(scanner: BagScanner, root: Path, clock: Clock):
    # rosbag2 writes metadata.yaml before it closes the last file: the footer may not be there yet
    folder = root / "bag"
    write_mcap(folder / "bag_0.mcap", finish=False)
    write_metadata(folder, ["bag_0.mcap"])
    assert closed(scanner.scan([root], {})) == {}
    clock.now += IDLE_S - 1
    assert closed(scanner.scan([root], {})) == {}
    clock.now += 1
    (bag,) = scanner.scan([root], {}).closed
    assert (bag.run_id, bag.application, bag.why) == ("bag", ROSBAG2, "idle")


def test_earlier_splits_are_closed_once_the_next_exists(scanner: BagScanner, root: Path):
    folder = root / "bag"
    first = write_mcap(folder / "bag_0.mcap")
    second = write_mcap(folder / "bag_1.mcap")
    current = write_mcap(folder / "bag_2.mcap", finish=False)  # being recorded: no metadata.yaml yet
    scan = scanner.scan([root], {})
    bags = closed(scan)
    assert sorted(bags) == [real(first), real(second)]
    assert {(b.run_id, b.application, b.why) for b in bags.values()} == {("bag", ROSBAG2, "next split")}
    assert real(current) in scan.pending


def test_a_split_without_its_footer_is_not_closed_by_the_next_one(scanner: BagScanner, root: Path, clock: Clock):
    # rosbag2 opens split N+1 before it closes split N
    folder = root / "bag"
    first = write_mcap(folder / "bag_0.mcap", finish=False)
    write_mcap(folder / "bag_1.mcap", finish=False)
    assert closed(scanner.scan([root], {})) == {}
    clock.now += IDLE_S
    bags = closed(scanner.scan([root], {}))
    assert bags[real(first)].why == "idle" and len(bags) == 2


def test_the_last_split_of_a_recording_bag_waits(scanner: BagScanner, root: Path, clock: Clock):
    folder = root / "bag"
    only = write_mcap(folder / "bag_0.mcap")  # its footer is written, but nothing says it is the last
    assert closed(scanner.scan([root], {})) == {}
    clock.now += IDLE_S
    assert closed(scanner.scan([root], {}))[real(only)].why == "idle"


def test_metadata_written_later_closes_the_files_it_lists(scanner: BagScanner, root: Path):
    folder = root / "bag"
    files = [write_mcap(folder / "bag_0.mcap"), write_mcap(folder / "bag_1.mcap")]
    assert list(closed(scanner.scan([root], {}))) == [real(files[0])]
    write_metadata(folder, ["bag_0.mcap"])  # a metadata.yaml the scanner read before it lists the last
    assert list(closed(scanner.scan([root], {}))) == [real(files[0])]
    write_metadata(folder, ["bag_0.mcap", "bag_1.mcap"])
    os.utime(folder / "metadata.yaml", ns=(1, 1))  # changed, whatever the file system's mtime resolution
    assert sorted(closed(scanner.scan([root], {}))) == [real(f) for f in files]


def test_metadata_paths_with_the_folder_in_front_are_matched_by_name(scanner: BagScanner, root: Path):
    folder = root / "old-bag"
    file = write_mcap(folder / "recording.mcap")  # not named as rosbag2 names splits
    write_metadata(folder, ["recording.mcap"], prefix_folder=True)
    (bag,) = scanner.scan([root], {}).closed
    assert (bag.path, bag.run_id, bag.application, bag.why) == (real(file), "old-bag", ROSBAG2, "metadata.yaml")


def test_a_metadata_file_that_is_no_bags_is_not_trusted(scanner: BagScanner, root: Path, clock: Clock):
    folder = root / "bag"
    write_mcap(folder / "bag_0.mcap")
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")  # half written
    assert closed(scanner.scan([root], {})) == {}
    clock.now += IDLE_S
    (bag,) = scanner.scan([root], {}).closed
    assert (bag.run_id, bag.application) == ("bag", ROSBAG2)  # named as rosbag2 names its splits


def test_metadata_files_reads_both_lists_and_refuses_what_is_not_a_bags(tmp_path: Path):
    write_metadata(tmp_path, ["a_0.mcap", "a_1.mcap"], prefix_folder=True)
    assert metadata_files((tmp_path / "metadata.yaml").read_text()) == {"a_0.mcap", "a_1.mcap"}
    assert metadata_files(
        "rosbag2_bagfile_information:\n  relative_file_paths: []\n  files:\n    - path: x.mcap\n"
    ) == {"x.mcap"}
    for text in ("", "- a\n- b\n", "other: 1\n", "rosbag2_bagfile_information: 3\n", ": : :\n  - ["):
        assert metadata_files(text) is None, text
    assert metadata_files("rosbag2_bagfile_information:\n  relative_file_paths: 7\n") is None


# --- lone MCAP files and the idle rule ------------------------------------------------------------


def test_a_lone_file_is_closed_once_idle_and_named_by_its_stem(scanner: BagScanner, root: Path, clock: Clock):
    lone = write_mcap(root / "drive 2024-01-31.mcap")
    nested = write_mcap(root / "day" / "arm.mcap")  # in a folder that is no bag's
    scan = scanner.scan([root], {})
    assert scan.closed == [] and sorted(scan.pending) == sorted([real(lone), real(nested)])
    clock.now += IDLE_S
    bags = closed(scanner.scan([root], {}))
    assert (bags[real(lone)].run_id, bags[real(lone)].application) == ("drive_2024-01-31", MCAP)
    assert (bags[real(nested)].run_id, bags[real(nested)].application) == ("arm", MCAP)
    assert {b.why for b in bags.values()} == {"idle"}


def test_a_file_that_changes_waits_the_idle_time_again(scanner: BagScanner, root: Path, clock: Clock):
    path = write_mcap(root / "lone.mcap", finish=False)
    scanner.scan([root], {})
    clock.now += IDLE_S - 5
    append(path)
    assert closed(scanner.scan([root], {})) == {}
    clock.now += IDLE_S - 1
    assert closed(scanner.scan([root], {})) == {}  # 29 s since it changed
    clock.now += 1
    (bag,) = scanner.scan([root], {}).closed
    assert bag.stamp.size == path.stat().st_size


def test_a_new_scanner_waits_the_idle_time_afresh(root: Path, clock: Clock):
    write_mcap(root / "lone.mcap")
    BagScanner(IDLE_S, clock=clock).scan([root], {})
    clock.now += IDLE_S
    assert BagScanner(IDLE_S, clock=clock).scan([root], {}).closed == []  # a restarted agent saw it just now


def test_an_idle_file_that_is_no_mcap_is_closed_and_said_so(scanner: BagScanner, root: Path, clock: Clock):
    (root / "notes.mcap").write_text("not an mcap file at all\n")
    (root / "empty.mcap").write_bytes(b"")
    scanner.scan([root], {})
    clock.now += IDLE_S
    bags = closed(scanner.scan([root], {}))
    assert {os.path.basename(p) for p in bags} == {"notes.mcap", "empty.mcap"}
    assert not any(b.is_mcap for b in bags.values())


# --- what was settled, what is skipped --------------------------------------------------------------


def test_settled_files_are_skipped_until_they_change(scanner: BagScanner, root: Path):
    (file,) = write_bag(root / "bag")
    (bag,) = scanner.scan([root], {}).closed
    settled = {bag.path: bag.stamp}
    scan = scanner.scan([root], settled)
    assert scan.closed == [] and scan.pending == [] and scan.found == {bag.path}
    write_mcap(file, messages=5)  # rewritten: another size
    (again,) = scanner.scan([root], settled).closed
    assert again.path == bag.path and again.stamp != bag.stamp


def test_hidden_and_temporary_files_and_hidden_folders_are_left_alone(scanner: BagScanner, root: Path, clock: Clock):
    for name in (".hidden.mcap", "~lock.mcap", "#autosave.mcap", "a.mcap.part", "bag_0.mcap.zstd", "x.db3", ".mcap"):
        write_mcap(root / name)
    write_mcap(root / ".trash" / "old.mcap")
    kept = write_mcap(root / "kept.mcap")
    scanner.scan([root], {})
    clock.now += IDLE_S
    scan = scanner.scan([root], {})
    assert scan.found == {real(kept)} and [b.path for b in scan.closed] == [real(kept)]


def test_missing_roots_are_skipped_and_the_others_scanned(scanner: BagScanner, root: Path, tmp_path: Path):
    write_bag(root / "bag")
    scan = scanner.scan([tmp_path / "missing", root], {})
    assert scan.roots == (real(root),) and len(scan.closed) == 1


def test_a_watched_folder_that_is_itself_a_bag(scanner: BagScanner, tmp_path: Path):
    folder = tmp_path / "rosbag2_2024_02_01-08_00_00"
    write_bag(folder, splits=2)
    bags = scanner.scan([folder], {}).closed
    assert [b.run_id for b in bags] == ["rosbag2_2024_02_01-08_00_00"] * 2


# --- names ------------------------------------------------------------------------------------------


def test_bag_names():
    assert is_bag_name("bag_0.mcap") and is_bag_name("a.mcap")
    for name in (".mcap", ".a.mcap", "~a.mcap", "#a.mcap#", "a.mcap.part", "a.mcap.zstd", "a.rrd", "a.MCAP"):
        assert not is_bag_name(name), name


def test_split_numbers():
    assert split_of("bag", "bag_0.mcap") == 0 and split_of("bag", "bag_12.mcap") == 12
    for name in ("bag.mcap", "bag_.mcap", "bag_x.mcap", "other_0.mcap", "bag_0.db3", "bag_².mcap"):
        assert split_of("bag", name) is None, name


@pytest.mark.parametrize(
    ("name", "run_id"),
    [
        ("rosbag2_2024_01_31-12_00_00", "rosbag2_2024_01_31-12_00_00"),
        ("drive 7: yard", "drive_7__yard"),
        ("Prüfung", "Pr_fung"),
        ("", "bag"),
        (".", "bag."),
        ("..", "bag.."),
    ],
)
def test_run_ids_are_ids_the_depot_takes(name: str, run_id: str):
    assert run_id_for(name) == run_id
    assert check_id("run id", run_id_for(name)) == run_id


def test_long_names_keep_their_start_and_stay_apart():
    a, b = run_id_for("x" * 200 + "a"), run_id_for("x" * 200 + "b")
    assert len(a) == len(b) == ID_LENGTH and a != b and a.startswith("x" * 100)
    assert check_id("run id", a) == a and run_id_for("x" * ID_LENGTH) == "x" * ID_LENGTH


def test_an_unreadable_file_waits_with_one_warning(
    scanner: BagScanner, root: Path, clock: Clock, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
):
    # (the tests run as root, whom permissions do not stop: the refusal is made up)
    path = write_mcap(root / "locked.mcap")

    def refused(name: str, *args: object, **kwargs: object) -> object:
        if str(name) == real(path):
            raise PermissionError(13, "Permission denied", str(name))
        return open(name, *args, **kwargs)  # type: ignore[call-overload]

    monkeypatch.setattr(bags_module, "open", refused, raising=False)
    scanner.scan([root], {})
    clock.now += IDLE_S
    for _ in range(3):
        scan = scanner.scan([root], {})
        assert scan.closed == [] and scan.pending == [real(path)]  # not called "no MCAP file": it waits
    assert caplog.text.count("cannot be read") == 1
    monkeypatch.undo()
    (bag,) = scanner.scan([root], {}).closed
    assert bag.is_mcap
