"""Power cuts on cards other tools prepared: ``mkfs.fat`` and mtools, not maglog.

Three cards, each partitioned (an MBR written here, as fdisk would: one FAT32 LBA partition
from sector 2048), formatted by ``mkfs.fat`` and filled by mtools (long names, so the root
directory spans many clusters; ~150 files; a subdirectory; an old ``LOG00007.TXT`` so the
numbers go on from it; every other small file deleted, so the free space is fragmented):

* ``512`` — 512-byte clusters, nearly full: the little free space left is in the holes, and
  the second or third recording fills the card;
* ``4k`` — 4 KiB clusters, every hole one cluster: each cluster of a log is somewhere else;
* ``32k`` — 32 KiB clusters (a 2.1 GB card, as SD cards are formatted).

On each, the logger records (the firmware, sw/app.py, on the transaction-level model), the
power is cut after N blocks, it comes back (a new model on the same card) and records again,
and for the double cuts the power is cut again, during the repair at mount or the second
recording, and comes back once more for a third recording that ends with the button. Every
image left (after each cut, and the last, closed cleanly) is judged:

* after a cut, ``fsck.fat -n`` says nothing beyond what the power-loss rule of DESIGN.md
  allows (:data:`~tests.system.test_power_cut.ALLOWED_FSCK`: dirty bit, lost clusters and
  the forms a cut leaves them in, a stale free count); after the recording that ends with
  the button, nothing at all (the repair at mount left nothing for it to find);
* every file the other tools wrote reads back unchanged (calib.card), and so does every log
  of an earlier run: nothing synced is lost, by a cut or by a repair;
* each log holds whole frames of its own run's recording, from the first (the recording
  starts at the button), and after a cut at least what the last sync before it made
  durable (from the traced reference run).

The default suite judges two double cuts on the 512-byte card (the second during the
repair, then during the recording); the slow suite the whole
campaign (:data:`CUTS` per card, as single and as double cuts).
"""

import collections
import random
import re
import subprocess

import pytest

from maglog.calib.card import open_card
from maglog.hw.arch import fat32 as arch
from maglog.sim.models.card_image import TracingImage
from maglog.sim.models.logger import LoggerModel
from maglog.sim.stimulus import sentences
from maglog.sim.stimulus.system import SystemScenario, Timeline, short_scenario
from maglog.sw.app import AppSettings, FwError, LoggerApp, State
from maglog.sw.fat32 import Volume

from ..sw.test_fat32 import fsck_findings, mtools_env
from .test_power_cut import Layout, fsck_kinds, frame_prefix, log_entry_size

MiB = 1 << 20
PARTITION_LBA = 2048
SEED = 23
#: Card name → (bytes, sectors a cluster, fill): see the module's docstring.
CARDS = {
    "512": (40 * MiB, 1, "nearly full"),
    "4k": (272 * MiB, 8, "one-cluster holes"),
    "32k": (2100 * MiB, 64, "one-cluster holes"),
}
#: Cut instants per card of the slow campaign, each judged as single cuts (cut, power up,
#: record, stop) and as double cuts (cut, power up, cut again, power up, record, stop).
CUTS = {"512": 10, "4k": 12, "32k": 12}
#: The default suite's double cuts on the 512-byte card.
QUICK_DOUBLE_CUTS = 2
#: Runs after the first start the recording here (after the repair at mount: ~1 s).
LATER_PRESS = 1.5


# -- The cards --------------------------------------------------------------------------------

def _mbr(total_sectors):
    """A DOS partition table with one FAT32 (LBA) partition from :data:`PARTITION_LBA` to the
    end, as ``fdisk`` writes it."""
    mbr = bytearray(512)
    entry = arch.MBR_PARTITION_TABLE
    mbr[entry + arch.PART_TYPE] = 0x0C
    mbr[entry + 1:entry + 4] = bytes([0xFE, 0xFF, 0xFF])          # CHS: use the LBA
    mbr[entry + 5:entry + 8] = bytes([0xFE, 0xFF, 0xFF])
    mbr[entry + 8:entry + 12] = PARTITION_LBA.to_bytes(4, "little")
    mbr[entry + 12:entry + 16] = (total_sectors - PARTITION_LBA).to_bytes(4, "little")
    mbr[510:512] = b"\x55\xaa"
    return bytes(mbr)


def _mtools(tool, image, *args):
    subprocess.run([tool, "-i", f"{image}@@{PARTITION_LBA * 512}", *args], check=True,
                   capture_output=True, env=mtools_env(), timeout=300)


def _free_bytes(fsck, image, tmp_path):
    """Free bytes of the partition, from fsck.fat's summary (clusters used/total)."""
    from ..sw.test_fat32 import copy_range_sparse, partition
    offset, length = partition(image)
    copy = tmp_path / "free.img"
    copy_range_sparse(image, offset, length, copy)
    result = subprocess.run([fsck, "-n", "-v", str(copy)], capture_output=True, text=True,
                            timeout=120)
    copy.unlink()
    cluster = int(next(line.split()[0] for line in result.stdout.splitlines()
                       if line.strip().endswith("bytes per cluster")))
    used, total = (int(n) for n in result.stdout.strip().splitlines()[-1]
                   .split(",")[-1].split()[0].split("/"))
    return (total - used) * cluster, cluster


def make_card(name, folder, tools):
    """The card ``name`` of :data:`CARDS` at ``folder / name.img``; returns its path."""
    size, spc, fill = CARDS[name]
    path = folder / f"{name}.img"
    with open(path, "wb") as f:
        f.write(_mbr(size // 512))
        f.truncate(size)
    subprocess.run([tools["mkfs.fat"], "-F", "32", "-s", str(spc), "-S", "512", "-n", "FOREIGN",
                    "-h", str(PARTITION_LBA), f"--offset={PARTITION_LBA}", "-i", "c0ffee00",
                    str(path), str((size - PARTITION_LBA * 512) // 1024)],
                   check=True, capture_output=True)
    rng = random.Random(f"{SEED}-{name}")
    cluster = spc * 512
    upload = folder / f"{name}-upload"
    upload.mkdir()
    small = []
    for k in range(150):
        # Long names (two long-name entries each): the root spans many clusters.
        file = upload / f"Flight {k:03d} magnetometer notes.txt"
        file.write_bytes(b"note %03d " % k * rng.randrange(1, cluster // 9 + 1))
        small.append(file)
    old_log = upload / "LOG00007.TXT"
    old_log.write_bytes(b"$an old log of another logger\r\n" * 40)
    _mtools(tools["mcopy"], path, *map(str, small), str(old_log), "::")
    _mtools(tools["mmd"], path, "::Survey data 2026")
    inner = []
    for k in range(8):
        file = upload / f"line {k:02d} raw.csv"
        file.write_bytes(b"%d,%d\n" % (k, k * k) * rng.randrange(10, 400))
        inner.append(file)
    _mtools(tools["mcopy"], path, *map(str, inner), "::Survey data 2026")
    if fill == "nearly full":
        # A filler leaves 16 KiB besides the holes the deletions below make: the first
        # recording (about 11 KB) fits, the second fills the card.
        free, _ = _free_bytes(tools["fsck.fat"], path, folder)
        filler = upload / "filler recording.bin"
        with open(filler, "wb") as f:
            f.write(bytes(free - 16 * 1024))
        deleted = small[1:40:4]                 # ten one-cluster holes, early on the card
        _mtools(tools["mcopy"], path, str(filler), "::")
    else:
        deleted = small[1::2]
    _mtools(tools["mdel"], path, *(f"::{file.name}" for file in deleted))
    return path


def files_of(path):
    """Every file on the card but the logger's new logs: ``{path: bytes}`` (calib.card)."""
    found = {}
    with open_card(path) as card:
        folders = ["/"]
        while folders:
            folder = folders.pop()
            for entry in card.listdir(folder):
                full = folder.rstrip("/") + "/" + entry.name
                if entry.is_dir:
                    folders.append(full)
                else:
                    found[full] = card.read(full)
    return found


# -- The recordings ---------------------------------------------------------------------------

def scenario(press, seed):
    """A recording from ``press`` for a second: magnetometer frames every 5 ms from 50 ms
    after the press, cesium every 20 ms, a fix (a flush) every 0.1 s; the stop 1.1 s after
    the press."""
    base = short_scenario()
    when = base.timestamp
    seconds_of_day = when.hour * 3600 + when.minute * 60 + when.second
    line = Timeline(base.channels)
    line.add(1, press - 0.2, sentences.zda(when))
    rng = random.Random(seed)
    events, start = [], press + 0.05
    for n in range(200):
        events.append((start + 0.005 * n, 0, sentences.pmag1(
            n, *(rng.uniform(-5e4, 5e4) for _ in range(3)))))
    for n in range(50):
        events.append((start + 0.0037 + 0.020 * n, 2,
                       sentences.cesium(rng.uniform(48e3, 52e3), rng.randrange(1000, 2000))))
    for n in range(10):
        events.append((start + 0.0013 + 0.1 * n, 1,
                       sentences.gga(seconds_of_day + n, 47.3769, 8.5417)))
    for at, channel, frame in sorted(events, key=lambda e: (e[0], e[1])):
        line.add(channel, at, frame)
    result = SystemScenario(channels=base.channels, clk_freq=base.clk_freq,
                            bursts=line.bursts, presses=[press, press + 1.1],
                            until=press + 1.3, timestamp=when)
    result.check_quiet(0.015)
    return result


def record(card, scene, cut=None, mounted=None):
    """Run the firmware on ``card`` (a TracingImage) through ``scene``, cut after ``cut``
    blocks if given; returns ``(RunResult, [LoggerApp])``. ``mounted`` (a list) gets the
    blocks stored when the first mount ended."""
    model = LoggerModel(card, clk_freq=scene.clk_freq, channels=scene.channels,
                        debounce_s=scene.debounce_s)
    model.play(scene)
    if cut is not None:
        model.cut_power(after_blocks=cut)
    apps = []

    async def firmware(bus):
        app = LoggerApp(bus, model.memory_map, sys_clock_hz=model.clk_freq,
                        settings=AppSettings())
        apps.append(app)
        await app.run()

    if mounted is None:
        return model.run(firmware, until=scene.until), apps
    mount = Volume.mount.__func__

    async def watched(cls, *args, **kwargs):
        volume = await mount(cls, *args, **kwargs)
        mounted.append(len(card.writes))
        return volume

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Volume, "mount", classmethod(watched))
        return model.run(firmware, until=scene.until), apps


class Campaign:
    """One card: its blank image, old files, and the traced reference of the first run."""

    def __init__(self, name, folder, tools):
        self.name, self.folder, self.tools = name, folder, tools
        #: Where the second cuts fell (see :meth:`run`).
        self.stats = collections.Counter()
        self.blank = make_card(name, folder, tools)
        self.old = files_of(self.blank)
        self.scenes = [scenario(0.3, 1), scenario(LATER_PRESS, 2), scenario(LATER_PRESS, 3)]
        card = TracingImage.load(self.blank)
        result, apps = record(card, self.scenes[0])
        assert not result.power_cut and len(apps) == 1
        self.writes = len(card.writes)
        logs = sorted(set(files_of_saved(card, folder / "ref.img")) - set(self.old))
        assert logs == ["/LOG00008.TXT"], logs
        # The sizes the first run made durable: each write of the log's entry.
        self.syncs = [(index, size) for index, (_, data) in enumerate(card.writes, 1)
                      if (size := log_entry_size(data, "LOG00008.TXT")) is not None]
        layout = Layout.of(card)
        self.fat_writes = [index for index, (lba, _) in enumerate(card.writes, 1)
                           if layout.fat_start <= lba < layout.data_start]

    def synced_at(self, cut):
        size = None
        for index, made in self.syncs:
            if index > cut:
                break
            size = made
        return size

    def cuts(self, count, seed):
        """``count`` seeded first-run cut instants, half just after FAT writes (where a cut
        leaves lost clusters or a chain longer than the file), half anywhere."""
        rng = random.Random(f"{seed}-{self.name}")
        fat = rng.sample(self.fat_writes, min(count // 2, len(self.fat_writes)))
        rest = sorted(set(range(1, self.writes)) - set(fat))
        return sorted(fat + rng.sample(rest, count - len(fat)))

    def run(self, first_cut, second_cut=None):
        """Cut, power up (record, or cut again and power up once more to record), stop:
        the problems found in every image left, and how many images were judged.
        ``second_cut`` is ``(where, fraction)``: the second run's cut falls at ``fraction``
        of the blocks it stores during the mount (``"mount"``: the repair) or after it
        (``"record"``), as an uncut trial of the same run shows."""
        problems, judged = [], 0
        image = self.folder / f"run-{first_cut}-{second_cut}.img"
        card = TracingImage.load(self.blank)
        kept = {}                               # earlier runs' logs: name -> bytes
        cuts = [first_cut] + ([second_cut] if second_cut is not None else [])
        for number, scene in enumerate(self.scenes[:len(cuts) + 1]):
            cut = cuts[number] if number < len(cuts) else None
            if number == 1 and cut is not None:
                trial, mounted = TracingImage.load(image), []
                record(trial, scene, mounted=mounted)
                kind, fraction = cut
                at_mount = mounted[0] if mounted else len(trial.writes)
                # (A clean volume's mount writes nothing: cut while recording then.)
                low, high = ((1, at_mount) if kind == "mount" and at_mount
                             else (at_mount + 1, len(trial.writes) - 1))
                cut = cuts[1] = low + int(fraction * (high - low)) if high >= low else None
            result, apps = record(card, scene, cut)
            card.save(image)
            judged += 1
            where = f"run {number + 1} (cuts {cuts})"
            if cut is not None and not result.power_cut:
                # The run ended before the cut: the card was closed by the button.
                cut = None
            if number == 1 and second_cut is not None:
                self.stats["second cut " + (
                    "not reached" if cut is None else "during the mount (repair)"
                    if apps[-1].volume is None else "while recording")] += 1
                if cut is None:
                    problems.append(f"{where}: no block to cut at {second_cut}")
            lines = fsck_findings(self.tools["fsck.fat"], image, self.folder)
            if cut is None:
                problems += [f"{where}, closed: fsck.fat: {line}" for line in lines]
                app = apps[-1]
                if app.error not in (FwError.NONE, FwError.CARD_FULL) or \
                        app.state not in (State.IDLE, State.FULL):
                    problems.append(f"{where}: the logger ended in {app.state.name} / "
                                    f"{app.error.name}: {app.message}")
            else:
                problems += [f"{where}, cut after {cut} blocks: fsck.fat: {line}"
                             for line in fsck_kinds(lines)[1]]
            try:
                now = files_of(image)
            except Exception as error:          # calib.card: a broken chain, ...
                problems.append(f"{where}: calib.card: {error}")
                break
            for path, data in self.old.items():
                if now.get(path) != data:
                    problems.append(f"{where}: the old file {path} changed")
            for path, data in kept.items():
                if now.get(path) != data:
                    problems.append(f"{where}: the log {path} of an earlier run changed "
                                    f"({len(data)} -> {len(now.get(path, b''))} bytes)")
            frames = scene.recorded_frames()
            for path in sorted(set(now) - set(self.old) - set(kept)):
                data = now[path]
                if not frame_prefix(data, frames):
                    problems.append(f"{where}: {path} ({len(data)} bytes) is not whole "
                                    f"frames of the recording from its first")
                volume = apps[-1].volume
                full = volume is not None and \
                    volume.free_count * volume.layout.cluster_bytes < 1024
                if cut is None and len(data) < len(b"".join(frames)) and not full:
                    problems.append(f"{where}: {path} holds {len(data)} bytes, not the whole "
                                    f"recording")
                synced = self.synced_at(cut) if number == 0 and cut is not None else None
                if synced is not None and len(data) < synced:
                    problems.append(f"{where}: {path} holds {len(data)} bytes, fewer than "
                                    f"the {synced} synced before the cut")
                kept[path] = data
            card = TracingImage.load(image)
        image.unlink(missing_ok=True)
        return problems, judged


@pytest.fixture(scope="module")
def tools(fat_tools, external):
    return dict(fat_tools, mtype=external.tool("mtype"))


_campaigns = {}


def campaign_of(name, tmp_path_factory, tools):
    if name not in _campaigns:
        _campaigns[name] = Campaign(name, tmp_path_factory.mktemp(f"foreign-{name}"), tools)
    return _campaigns[name]


def files_of_saved(card, path):
    card.save(path)
    try:
        return files_of(path)
    finally:
        path.unlink()


def test_the_cards_are_as_described(tmp_path_factory, tools):
    # The 512-byte card: over 150 files, a root of many clusters, little free space, in holes.
    campaign = campaign_of("512", tmp_path_factory, tools)
    assert len(campaign.old) >= 150
    card = TracingImage.load(campaign.blank)
    layout = Layout.of(card)
    assert layout.sectors_per_cluster == 1
    assert len(layout.chain(card, layout.root_cluster)) >= 20
    free, _ = _free_bytes(tools["fsck.fat"], campaign.blank, campaign.folder)
    assert 10 * 1024 < free < 40 * 1024, free
    assert len(campaign.fat_writes) >= 10


def test_double_cuts_on_a_nearly_full_card_of_others(tmp_path_factory, tools):
    campaign = campaign_of("512", tmp_path_factory, tools)
    rng = random.Random(SEED)
    failures, judged = {}, 0
    for first, where in zip(campaign.cuts(QUICK_DOUBLE_CUTS, seed=SEED), ["mount", "record"]):
        second = (where, rng.random())
        problems, count = campaign.run(first, second)
        judged += count
        if problems:
            failures[(first, second)] = problems
    assert failures == {}
    assert judged >= 2 * QUICK_DOUBLE_CUTS
    assert campaign.stats["second cut during the mount (repair)"] >= 1, campaign.stats


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CARDS))
@pytest.mark.parametrize("double", [False, True], ids=["single", "double"])
def test_power_cut_campaign_on_cards_of_others(tmp_path_factory, tools, name, double):
    campaign = campaign_of(name, tmp_path_factory, tools)
    rng = random.Random(f"{SEED}-{name}-{double}")
    failures, judged = {}, 0
    count = CUTS[name]
    for first in campaign.cuts(count, seed=f"{SEED}-{double}"):
        # The second cut: during the repair at mount, or during the recording after it.
        second = ((rng.choice(["mount", "record"]), rng.random()) if double else None)
        problems, number = campaign.run(first, second)
        judged += number
        if problems:
            failures[(first, second)] = problems
    kinds = collections.Counter(finding_kind(problem) for problems in failures.values()
                                for problem in problems)
    print(f"{name} {'double' if double else 'single'}: {count} "
          f"cut sequences, {judged} images judged, {len(failures)} sequences with findings "
          f"{dict(sorted(kinds.items()))}; {dict(sorted(campaign.stats.items()))}")
    assert failures == {}
    if double:
        assert campaign.stats["second cut during the mount (repair)"] >= 2, campaign.stats
        assert campaign.stats["second cut while recording"] >= 2, campaign.stats


def finding_kind(problem):
    """A problem line without its run and numbers (to count findings by kind)."""
    text = re.sub(r"^run \d+ \(cuts \[[\d, ]+\]\)", "", problem)
    text = re.sub(r"/LOG\d+\.TXT", "LOG", text)
    return re.sub(r"\d+", "N", text)
