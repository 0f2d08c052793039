"""Power cuts during a recording, on the logger model with the firmware (sw/app.py).

One reference recording is run with every block the card stores traced: its index (the
card had stored that many blocks once it was stored), its LBA and the region it hits
(boot, FSInfo, FAT 1, FAT 2, directory, data), and the phase of the firmware that wrote it
(creating the file, growing the root directory, a flush, closing the file). The file's sync
points come from the trace itself: each write of the directory sector holding the log's
entry makes the size in that entry durable.

The same recording is then run again, the power cut after N blocks
(``LoggerModel.cut_power(after_blocks=N)``), for seeded N spread over every block write,
every region and phase cut several times. Each image left behind must be recoverable:

* ``fsck.fat -n`` finds nothing but what :data:`ALLOWED_FSCK` lists: the dirty bit, lost
  clusters (also in the forms a cut between the FAT writes and the directory entry leaves:
  a chain longer than the size, FATs that differ only in the fresh clusters) and a stale
  free-cluster count;
* calib.card and mtools read the log, which holds every byte of the last sync before the
  cut and, beyond, nothing but a prefix of the recording (whole frames);
* the files that were on the card before are intact.

The default suite cuts :data:`QUICK_CUTS` instants (each special phase and a seeded few
per region); the slow suite all of :data:`FULL_CUTS`.
"""

import collections
import datetime as dt
import random
import re
import subprocess
from dataclasses import dataclass

import pytest

from maglog.calib.card import CardError, read_logs
from maglog.hw.arch import fat32 as arch
from maglog.sim.stimulus import sentences
from maglog.sim.models.card_image import TracingImage
from maglog.sim.models.logger import LoggerModel
from maglog.sim.stimulus.system import SystemScenario, Timeline, short_scenario
from maglog.sw import fat32
from maglog.sw.app import AppSettings, LoggerApp
from maglog.sw.fat32 import ImageFile, Volume, format_image

from ..sw.test_fat32 import fsck_findings, mtools_env, partition

MiB = 1 << 20
CARD_BYTES = 40 * MiB
#: 512-byte clusters: every flush allocates clusters, so every flush writes FAT sectors.
CLUSTER_BYTES = 512
#: Files on the card before the recording: they fill the root directory's first cluster
#: (the volume label and 15 entries), so creating the log grows the root directory; the
#: first one's clusters (3 .. 120) put the log six clusters before the end of FAT sector 0,
#: so the recording's chain crosses into FAT sector 1 (the linking sector written last).
EXISTING = {f"LOG{k:05d}.TXT": (b"$old %05d\r\n" % k) * (5_000 if k == 1 else 0)
            for k in range(1, 16)}
LOG_NAME = "LOG00016.TXT"
SEED = 11
FULL_CUTS = 220
QUICK_CUTS = 30
#: The slow campaign runs in this many tests (pytest -n 2 shares them out).
SLOW_PARTS = 4
#: Instants the quick suite cuts in every region, besides the special phases.
QUICK_PER_REGION = 3
REGIONS = ("boot", "fsinfo", "fat1", "fat2", "directory", "data")

#: What ``fsck.fat -n`` (4.2) may say about a card cut mid-recording, each line named.
#: Everything else it prints is a failure.
ALLOWED_FSCK = {
    # The volume was dirty (the firmware clears the clean bit at the first write).
    "dirty bit": r"Dirty bit is set\. Fs was not properly unmounted and some data may be "
                 r"corrupt\.",
    "dirty bit (fix)": r" Automatically removing dirty bit\.",
    # Lost clusters: allocated in the FAT, in no chain.
    "lost clusters": r"Reclaimed \d+ unused clusters? \(\d+ bytes\)\.",
    # The FAT sectors were written, the directory entry not yet: the chain is longer than
    # the size (the clusters past the size are lost clusters, fsck truncates the chain).
    "chain longer than size": r"/LOG\d{5}\.TXT",
    "chain longer than size (what)": r"  File size is \d+ bytes, cluster chain length is "
                                     r"> \d+ bytes\.",
    "chain longer than size (fix)": r"  Truncating file to \d+ bytes\.",
    # FAT 1 written, FAT 2 not yet: they differ only in clusters that are fresh.
    "FATs differ": r"FATs differ but appear to be intact\.",
    "FATs differ (fix)": r"  Using first FAT\.",
    # FSInfo not yet written: its free count is stale.
    "free count": r"Free cluster summary wrong \(\d+ vs\. really \d+\)",
    "free count (fix)": r"  Auto-correcting\.",
    "read only": r"Leaving filesystem unchanged\.",
    "exit status": r"exit status 1",
}
_ALLOWED = {name: re.compile(f"^{pattern}$") for name, pattern in ALLOWED_FSCK.items()}


def fsck_kinds(lines):
    """``(kinds, unknown)``: the names of :data:`ALLOWED_FSCK` the lines match, and the
    lines that match none."""
    kinds, unknown = set(), []
    for line in lines:
        name = next((name for name, pattern in _ALLOWED.items() if pattern.match(line)),
                    None)
        if name is None:
            unknown.append(line)
        else:
            kinds.add(name)
    return kinds, unknown


# -- The recording ----------------------------------------------------------------------------

def campaign_scenario():
    """Five seconds on the short scenario's fast lines: the GPS time while idle, then a
    recording from 0.3 s to 4.5 s of magnetometer frames every 5 ms, cesium frames every
    20 ms and a GGA fix (a flush) every 0.1 s: about 40 flushes of about 1 KiB each."""
    base = short_scenario()
    when = base.timestamp
    seconds_of_day = when.hour * 3600 + when.minute * 60 + when.second
    line = Timeline(base.channels)
    line.add(1, 0.1, sentences.zda(when))
    rng = random.Random(SEED)
    events = []
    for n in range(int((4.45 - 0.35) / 0.005)):
        events.append((0.35 + 0.005 * n, 0, sentences.pmag1(n, *(rng.uniform(-5e4, 5e4)
                                                                  for _ in range(3)))))
    for n in range(int((4.45 - 0.35) / 0.020)):
        events.append((0.3537 + 0.020 * n, 2, sentences.cesium(rng.uniform(48e3, 52e3),
                                                               rng.randrange(1000, 2000))))
    for n in range(int((4.45 - 0.35) / 0.1)):
        events.append((0.3513 + 0.1 * n, 1, sentences.gga(seconds_of_day + n, 47.3769,
                                                          8.5417)))
    for at, channel, frame in sorted(events, key=lambda e: (e[0], e[1])):
        line.add(channel, at, frame)
    scenario = SystemScenario(channels=base.channels, clk_freq=base.clk_freq,
                              bursts=line.bursts, presses=[0.3, 4.5], until=4.8,
                              timestamp=when)
    scenario.check_quiet(0.015)
    return scenario


def blank_card(path):
    """A formatted card holding :data:`EXISTING` (written by the firmware's own FAT32
    writer on the host, then closed clean)."""
    format_image(path, CARD_BYTES, cluster_bytes=CLUSTER_BYTES, volume_id=0x1234)
    stamp = dt.datetime(2026, 1, 2, 3, 4, 6)

    async def fill(device):
        volume = await Volume.mount(device)
        for name, data in EXISTING.items():
            log = await volume.create_log(stamp)
            assert log.name == name
            await log.append(data)
            await log.close(stamp)
        await volume.close()

    with ImageFile(path) as device:
        _run(fill(device))
    return path


def _run(coroutine):
    try:
        coroutine.send(None)
    except StopIteration as stop:
        return stop.value
    raise RuntimeError("the host-side FAT32 writer awaited something")


@dataclass(frozen=True)
class Layout:
    """Where the regions of the card's FAT32 volume lie (LBAs)."""
    partition_start: int
    fsinfo: int
    fat_start: int
    fat_sectors: int
    data_start: int
    sectors_per_cluster: int
    root_cluster: int

    @classmethod
    def of(cls, image):
        entry = image.read_block(0)[arch.MBR_PARTITION_TABLE:]
        start = int.from_bytes(entry[arch.PART_LBA_FIRST:arch.PART_LBA_FIRST + 4], "little")
        bs = image.read_block(start)

        def u(offset, size):
            return int.from_bytes(bs[offset:offset + size], "little")

        fat_start = start + u(arch.BPB_RSVD_SEC_CNT, 2)
        fat_sectors = u(arch.BPB_FAT_SZ32, 4)
        return cls(partition_start=start, fsinfo=start + u(arch.BPB_FS_INFO, 2),
                   fat_start=fat_start, fat_sectors=fat_sectors,
                   data_start=fat_start + u(arch.BPB_NUM_FATS, 1) * fat_sectors,
                   sectors_per_cluster=u(arch.BPB_SEC_PER_CLUS, 1),
                   root_cluster=u(arch.BPB_ROOT_CLUS, 4))

    def cluster_of(self, lba):
        return (lba - self.data_start) // self.sectors_per_cluster + arch.FIRST_DATA_CLUSTER

    def fat_entry(self, image, cluster):
        lba, offset = divmod(cluster * 4, arch.SECTOR_BYTES)
        block = image.read_block(self.fat_start + lba)
        return int.from_bytes(block[offset:offset + 4], "little") & arch.FAT_ENTRY_MASK

    def chain(self, image, first):
        chain, cluster = [], first
        while arch.FIRST_DATA_CLUSTER <= cluster < arch.FAT_EOC_MIN:
            chain.append(cluster)
            cluster = self.fat_entry(image, cluster)
        return chain

    def region(self, lba, directory):
        if lba < self.fat_start:
            return "fsinfo" if lba == self.fsinfo else "boot"
        if lba < self.fat_start + self.fat_sectors:
            return "fat1"
        if lba < self.data_start:
            return "fat2"
        return "directory" if self.cluster_of(lba) in directory else "data"


def log_entry_size(block, name):
    """The size in ``name``'s directory entry if the directory sector ``block`` holds it."""
    raw = (name[:8] + name[9:]).encode("ascii")
    for offset in range(0, arch.SECTOR_BYTES, arch.DIR_ENTRY_BYTES):
        if block[offset:offset + arch.DIR_NAME_BYTES] == raw:
            return int.from_bytes(block[offset + arch.DIR_FILE_SIZE:
                                        offset + arch.DIR_FILE_SIZE + 4], "little")
    return None


@dataclass(frozen=True)
class Write:
    """Block write ``index`` (1-based) of the reference recording."""
    index: int
    lba: int
    region: str
    phase: str          # "mount", "create", "grow root", "flush", "close"


@dataclass
class Reference:
    scenario: SystemScenario
    blank: object       # path of the blank card
    writes: list        # [Write]
    syncs: list         # [(index, size)]: after block `index` the file had `size` bytes
    recording: bytes    # the log file of the uncut recording
    frames: list        # the recorded frames
    sync: object = None # a replacement for LogFile.sync (a deliberately broken one)

    def synced_at(self, cut):
        """The size the last sync at or before block ``cut`` made durable (None: the
        file's entry was not written yet)."""
        size = None
        for index, made in self.syncs:
            if index > cut:
                break
            size = made
        return size


def model_of(scenario, card):
    model = LoggerModel(card, clk_freq=scenario.clk_freq, channels=scenario.channels,
                        debounce_s=scenario.debounce_s)
    model.play(scenario)
    return model


def record(scenario, card, *, cut=None, marks=None):
    """Run the recording on ``card`` (a :class:`TracingImage`), cut after ``cut`` blocks if
    given; returns ``(RunResult, apps)``. ``marks`` (a list) gets ``("flush", blocks
    stored so far)`` at the start of every flush (the firmware's fault hook)."""
    model = model_of(scenario, card)
    if cut is not None:
        model.cut_power(after_blocks=cut)
    apps = []

    async def fault(app, point):
        if marks is not None and point == "flush":
            marks.append(("flush", len(card.writes)))

    async def firmware(bus):
        app = LoggerApp(bus, model.memory_map, sys_clock_hz=model.clk_freq,
                        settings=AppSettings(fault=fault))
        apps.append(app)
        await app.run()

    return model.run(firmware, until=scenario.until), apps


def _marking(marks, card, owner, name, label):
    """``owner.name`` (an async method) that appends ``(label, blocks stored)`` before and
    ``(label + " end", blocks stored)`` after it runs."""
    original = getattr(owner, name)

    async def wrapper(*args, **kwargs):
        marks.append((label, len(card.writes)))
        result = await original(*args, **kwargs)
        marks.append((label + " end", len(card.writes)))
        return result

    return wrapper


def make_reference(tmp_path, *, sync=None):
    """Run the uncut recording once and trace it (see the module's docstring); ``sync``
    replaces :meth:`LogFile.sync` for the recording (not for the blank card's files)."""
    scenario = campaign_scenario()
    blank = blank_card(tmp_path / "blank.img")
    card = TracingImage.load(blank)
    marks = []
    with pytest.MonkeyPatch.context() as patch:
        # Phases: wrap the FAT32 writer's create, root growth and close (the flushes are
        # marked by the firmware's own fault hook).
        for owner, name, label in ((Volume, "create_log", "create"),
                                   (Volume, "_grow_root", "grow root"),
                                   (fat32.LogFile, "close", "close")):
            patch.setattr(owner, name, _marking(marks, card, owner, name, label))
        if sync is not None:
            patch.setattr(fat32.LogFile, "sync", sync)
        result, apps = record(scenario, card, marks=marks)
    assert not result.power_cut and result.resets == 0
    (app,) = apps
    assert app.flushes >= 30, app.flushes
    path = tmp_path / "reference.img"
    card.save(path)
    logs = dict(read_logs(path))
    frames = scenario.recorded_frames()
    recording = b"".join(frames)
    assert logs[LOG_NAME] == recording

    layout = Layout.of(card)
    directory = set(layout.chain(card, layout.root_cluster))
    assert len(directory) == 2                  # the root directory grew by a cluster
    file_chain = layout.chain(card, layout.cluster_of(next(
        lba for lba, _ in card.writes if layout.region(lba, directory) == "data")))
    fat_sectors = {cluster * 4 // arch.SECTOR_BYTES for cluster in file_chain}
    assert len(fat_sectors) >= 2                # the chain crosses a FAT sector boundary

    spans = {}
    for label, at in marks:
        if label.endswith(" end"):
            spans[label.removesuffix(" end")][-1][1] = at
        elif label != "flush":
            spans.setdefault(label, []).append([at, None])
    first_flush = min(at for label, at in marks if label == "flush")

    def phase(index):
        for name in ("grow root", "create", "close"):
            for start, end in spans.get(name, ()):
                if start < index <= end:
                    return name
        return "flush" if index > first_flush else "mount"

    writes = [Write(i, lba, layout.region(lba, directory), phase(i))
              for i, (lba, _) in enumerate(card.writes, 1)]
    syncs = []
    for write, (lba, data) in zip(writes, card.writes):
        if write.region == "directory":
            size = log_entry_size(data, LOG_NAME)
            if size is not None:
                syncs.append((write.index, size))
    assert syncs[0][1] == 0 and syncs[-1][1] == len(recording)
    return Reference(scenario, blank, writes, syncs, recording, frames, sync)


def choose_cuts(reference, count, *, seed=SEED, per_region=None):
    """``count`` distinct cut instants (1 .. last block): every write of the special phases
    (create, grow root, close), then ``per_region`` seeded instants in each region (all of
    a region's writes if it has fewer; default: an equal share), then seeded instants over
    the rest."""
    rng = random.Random(seed)
    cuts = {w.index for w in reference.writes if w.phase in ("create", "grow root", "close")}
    by_region = {}
    for write in reference.writes:
        by_region.setdefault(write.region, []).append(write.index)
    share = per_region if per_region is not None else count // (2 * len(by_region))
    for region in sorted(by_region):
        pool = sorted(set(by_region[region]) - cuts)
        cuts.update(rng.sample(pool, min(share, len(pool))))
    rest = sorted({w.index for w in reference.writes} - cuts)
    cuts.update(rng.sample(rest, max(0, min(count - len(cuts), len(rest)))))
    return sorted(cuts)


def mtype(tool, image, name):
    """``name``'s bytes as mtools reads them, or None when it cannot."""
    offset, _ = partition(image)
    result = subprocess.run([tool, "-i", f"{image}@@{offset}", f"::{name}"],
                            capture_output=True, env=mtools_env(), timeout=60)
    return result.stdout if result.returncode == 0 else None


def frame_prefix(data, frames):
    """Whether ``data`` is the first k frames joined, for some k."""
    joined = 0
    for frame in frames:
        if joined == len(data):
            return True
        joined += len(frame)
        if joined > len(data):
            return False
    return joined == len(data)


def cut_verdict(reference, cut, tmp_path, tools):
    """Cut the recording after block ``cut`` and judge the card: ``(problems, fsck kinds)``
    (no problems: the card is as the module's docstring requires)."""
    card = TracingImage.load(reference.blank)
    with pytest.MonkeyPatch.context() as patch:
        if reference.sync is not None:
            patch.setattr(fat32.LogFile, "sync", reference.sync)
        result, _ = record(reference.scenario, card, cut=cut)
    problems = []
    if not result.power_cut:
        problems.append("the power was not cut")
    if len(card.writes) != cut or any(
            lba != write.lba for (lba, _), write in zip(card.writes, reference.writes)):
        problems.append(f"the cut run stored {len(card.writes)} blocks, not the reference's "
                        f"first {cut}")
    path = tmp_path / f"cut{cut}.img"
    card.save(path)
    try:
        kinds, unknown = fsck_kinds(fsck_findings(tools["fsck.fat"], path, tmp_path))
        problems += [f"fsck.fat: {line}" for line in unknown]
        try:
            logs = dict(read_logs(path))
        except CardError as error:
            problems.append(f"calib.card: {error}")
            return problems, kinds
        for name, data in EXISTING.items():
            if logs.get(name) != data:
                problems.append(f"calib.card reads the existing {name} differently")
        synced = reference.synced_at(cut)
        log = logs.get(LOG_NAME)
        if synced is None:
            if log is not None:
                problems.append(f"{LOG_NAME} exists before its entry was written")
        elif log is None:
            problems.append(f"{LOG_NAME} is missing (synced: {synced} bytes)")
        else:
            if len(log) < synced:
                problems.append(f"{LOG_NAME} holds {len(log)} bytes, fewer than the "
                                f"{synced} synced")
            if reference.recording[:len(log)] != log or \
                    not frame_prefix(log, reference.frames):
                problems.append(f"{LOG_NAME} ({len(log)} bytes) is not a prefix of the "
                                f"recording's frames")
            if mtype(tools["mtype"], path, LOG_NAME) != log:
                problems.append(f"mtools reads {LOG_NAME} differently from calib.card")
    finally:
        path.unlink()
    return problems, kinds


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return make_reference(tmp_path_factory.mktemp("power-cut"))


@pytest.fixture(scope="module")
def tools(fat_tools, external):
    return dict(fat_tools, mtype=external.tool("mtype"))


def campaign(reference, cuts, tmp_path, tools):
    """Cut at each of ``cuts``: ``({cut: problems} of the failing ones, Counter of the
    fsck finding kinds seen)``."""
    failures, seen = {}, collections.Counter()
    for cut in cuts:
        problems, kinds = cut_verdict(reference, cut, tmp_path, tools)
        seen.update(kinds)
        if problems:
            write = reference.writes[cut - 1]
            failures[f"{cut} ({write.region}, {write.phase})"] = problems
    return failures, seen


def test_the_reference_recording_writes_every_region(reference):
    regions = collections.Counter(w.region for w in reference.writes)
    phases = collections.Counter(w.phase for w in reference.writes)
    assert set(regions) == {"fsinfo", "fat1", "fat2", "directory", "data"}
    assert phases["grow root"] >= 4 and phases["create"] >= 1 and phases["close"] >= 3
    # A sync a flush (about 40), the file's creation and its close; each made a size
    # durable that the next one only grows.
    sizes = [size for _, size in reference.syncs]
    assert len(sizes) >= 40 and sizes == sorted(sizes)
    assert reference.writes[reference.syncs[0][0] - 1].phase == "create"


def test_cut_instants_cover_every_region_and_phase(reference):
    for count, least in ((QUICK_CUTS, QUICK_PER_REGION), (FULL_CUTS, 20)):
        cuts = choose_cuts(reference, count,
                           per_region=QUICK_PER_REGION if count == QUICK_CUTS else None)
        assert len(cuts) == len(set(cuts)) >= count
        writes = [reference.writes[cut - 1] for cut in cuts]
        regions = collections.Counter(w.region for w in writes)
        assert all(regions[name] >= least for name in REGIONS if name != "boot"), regions
        special = {w.index for w in reference.writes
                   if w.phase in ("create", "grow root", "close")}
        assert special <= set(cuts)
    assert choose_cuts(reference, FULL_CUTS) == choose_cuts(reference, FULL_CUTS)


def test_power_cuts_leave_a_recoverable_card(reference, tmp_path, tools):
    cuts = choose_cuts(reference, QUICK_CUTS, per_region=QUICK_PER_REGION)
    failures, seen = campaign(reference, cuts, tmp_path, tools)
    assert failures == {}
    # The cuts hit a volume in use, some between a sync's FAT and its directory entry.
    assert "dirty bit" in seen and {"lost clusters", "chain longer than size"} & set(seen)


@pytest.mark.slow
@pytest.mark.parametrize("part", range(SLOW_PARTS))
def test_power_cuts_leave_a_recoverable_card_everywhere(reference, tmp_path, tools, part):
    # The full campaign in SLOW_PARTS parts (pytest -n 2 runs them side by side).
    cuts = choose_cuts(reference, FULL_CUTS)[part::SLOW_PARTS]
    failures, _ = campaign(reference, cuts, tmp_path, tools)
    assert failures == {}


async def _entry_before_fat_sync(self, timestamp):
    """A broken :meth:`LogFile.sync` (ring path, no appended tail): the directory entry
    first, then the FAT, then FSInfo."""
    volume = self.volume
    date, time = fat32.fat_date_time(timestamp)
    fat32._put16(self._entry, arch.DIR_WRT_DATE, date)
    fat32._put16(self._entry, arch.DIR_WRT_TIME, time)
    fat32._put16(self._entry, arch.DIR_FST_CLUS_HI, self._first >> 16)
    fat32._put16(self._entry, arch.DIR_FST_CLUS_LO, self._first & 0xFFFF)
    fat32._put32(self._entry, arch.DIR_FILE_SIZE, self.size)
    await self._write_entry()
    await volume._flush_fat()
    await volume._write_fsinfo()
    self._forget_before(self.size // volume.layout.cluster_bytes)


def test_the_campaign_catches_an_entry_written_before_the_fat(tmp_path, tools):
    # Break the sync order: a cut between the entry and the FAT leaves a size that the
    # chain on the card does not reach (a file pointing at clusters the FAT calls free).
    broken = make_reference(tmp_path, sync=_entry_before_fat_sync)
    writes = broken.writes[:60]
    cuts = [a.index for a, b in zip(writes, writes[1:])
            if a.phase == "flush" and a.region == "directory" and b.region == "fat1"][:4]
    assert len(cuts) == 4
    failures, _ = campaign(broken, cuts, tmp_path, tools)
    assert len(failures) == len(cuts)
    assert all(any(p.startswith("fsck.fat") for p in problems)
               for problems in failures.values()), failures
