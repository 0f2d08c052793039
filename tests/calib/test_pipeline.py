"""`maglog calibrate` on a card image made by independent FAT tools (mkfs.fat, mcopy)."""

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from maglog.sim.cli import main
from maglog.sim.scenario import make_flight

TOOLS = {name: shutil.which(name) or next(
    (str(p) for p in (Path("/usr/sbin") / name, Path("/sbin") / name) if p.exists()), None)
    for name in ("mkfs.fat", "mcopy")}
pytestmark = pytest.mark.skipif(
    not all(TOOLS.values()),
    reason="card images are built with mkfs.fat (dosfstools) and mcopy (mtools): "
           "run `make test`, which installs them")

FS_LBA = 2048
FS_SECTORS = 131072                   # 64 MiB: a legal FAT32 with one-sector clusters


def card_image(path, files):
    """A raw card image: an MBR with one FAT32 (LBA) partition at 1 MiB, formatted and
    filled by mkfs.fat and mcopy."""
    with open(path, "wb") as f:
        f.truncate((FS_LBA + FS_SECTORS) * 512)
        entry = struct.pack("<B3sB3sII", 0x00, b"\0\0\0", 0x0C, b"\0\0\0", FS_LBA, FS_SECTORS)
        f.seek(0x1BE)
        f.write(entry)
        f.seek(0x1FE)
        f.write(b"\x55\xAA")
    subprocess.run([TOOLS["mkfs.fat"], "-F", "32", "-s", "1", "--offset", str(FS_LBA),
                    "-h", str(FS_LBA), str(path), str(FS_SECTORS // 2)],
                   check=True, capture_output=True)
    for name, data in files.items():
        source = path.parent / name
        source.write_bytes(data)
        subprocess.run([TOOLS["mcopy"], "-i", f"{path}@@{FS_LBA * 512}", str(source),
                        f"::{name}"], check=True, capture_output=True)


@pytest.mark.parametrize("ref", ["cesium", "igrf"])
def test_calibrate_a_card_image(tmp_path, ref, capsys):
    flight = make_flight(coverage="uav", seconds=60, seed=5)
    image = tmp_path / "card.img"
    card_image(image, {"LOG00001.TXT": flight.log(), "NOTES.TXT": b"not a log\r\n"})
    out = tmp_path / "report"
    assert main(["calibrate", str(image), "--ref", ref, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "total-field RMS" in printed
    summary = json.loads((out / "parameters.json").read_text())
    k_true, c_true = flight.errors.truth()
    assert summary["log"] == "LOG00001.TXT"
    assert summary["rms_after_nT"] < 0.01 * summary["rms_before_nT"]
    if ref == "cesium":
        np.testing.assert_allclose(np.array(summary["K"]), k_true, atol=5e-4)
        np.testing.assert_allclose(summary["c"], c_true, atol=25.0)
    for name in ("report.md", "report.html", "figure7.png", "coverage.png", "residuals.png",
                 "allan.png"):
        assert (out / name).stat().st_size > 0


def test_errors_are_clear(tmp_path, capsys):
    garbage = tmp_path / "garbage.img"
    garbage.write_bytes(bytes(range(256)) * 64)
    assert main(["calibrate", str(garbage), "--out", str(tmp_path / "r")]) == 1
    assert "maglog: error:" in capsys.readouterr().err
    empty = tmp_path / "empty.img"
    card_image(empty, {"README.TXT": b"hello\r\n"})
    assert main(["calibrate", str(empty), "--out", str(tmp_path / "r")]) == 1
    assert "no LOG*.TXT" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "missing.img")]) == 1
    assert "no such file" in capsys.readouterr().err


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """A survey flight (calibration manoeuvre, then six lines in a wind) with the sensor
    yawed 5° in the airframe, as a plain log and an attitude file."""
    from maglog.sim.scenario import ErrorModel, make_survey
    flight = make_survey(errors=ErrorModel(mounting=(0.0, 0.0, 5.0)), seed=6)
    folder = tmp_path_factory.mktemp("survey")
    (folder / "LOG00002.TXT").write_bytes(flight.log())
    (folder / "attitude.csv").write_bytes(flight.attitude_csv())
    return folder


def test_heading_alignment_and_error_against_the_attitude(survey, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["calibrate", str(survey / "LOG00002.TXT"), "--attitude",
                 str(survey / "attitude.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "heading offset" in printed
    heading = json.loads((out / "parameters.json").read_text())["heading"]
    assert heading["legs_found"] == 6 and heading["attitude_known"]
    errors = heading["error_rms_deg"]
    # What stays on the legs is the frame's tilt (about ±1.4° here, flipping sign between
    # the reciprocal lines), which the course over ground cannot see.
    assert errors["legs_before_alignment"] > 2.5
    assert errors["legs_after_alignment"] < 0.5 * errors["legs_before_alignment"]
    assert errors["after_alignment"] < errors["before_alignment"]
    assert (out / "heading_error.png").stat().st_size > 0
    report = (out / "report.md").read_text()
    assert "## Heading" in report and "heading - course" in report
    page = (out / "report.html").read_text()
    assert "<h2>Heading</h2>" in page and page.count("<table>") == 2
    assert '<img src="heading_error.png">' in page and "<pre>" in page
    # Without the attitude the same log is aligned from level-flight headings alone.
    assert main(["calibrate", str(survey / "LOG00002.TXT"), "--out", str(tmp_path / "r2")]) == 0
    level = json.loads((tmp_path / "r2" / "parameters.json").read_text())["heading"]
    assert level["alignment"]["offset_deg"] == pytest.approx(
        heading["alignment"]["offset_deg"], abs=0.4)
    assert not (tmp_path / "r2" / "heading_error.png").exists()


@pytest.mark.parametrize("text,message", [
    (None, "no such attitude file"),
    ("", "is empty"),
    ("t,roll_deg,pitch_deg\n1,0,0\n", "lacks heading_deg"),
    ("t,roll_deg,pitch_deg,heading_deg\n1,0,0,10\n2,0,zero,10\n", ":3: not a number"),
    ("t,roll_deg,pitch_deg,heading_deg\n1,0,0,10\n2,0,0\n", ":3: 3 fields"),
    ("t,roll_deg,pitch_deg,heading_deg\n1,0,0,10\n", "at least 2 rows"),
    ("t,roll_deg,pitch_deg,heading_deg\n5,0,0,10\n5,0,0,10\n", "t must increase"),
    ("t,roll_deg,pitch_deg,heading_deg\n1,0,0,nan\n2,0,0,1\n", "not a finite number"),
    ("heading_deg,t,pitch_deg,roll_deg\n10,1,0,0\n10,2,0,0\n", "do not overlap"),
])
def test_attitude_file_errors(survey, tmp_path, capsys, text, message):
    path = tmp_path / "attitude.csv"
    if text is not None:
        path.write_text(text)
    assert main(["calibrate", str(survey / "LOG00002.TXT"), "--attitude", str(path),
                 "--out", str(tmp_path / "r")]) == 1
    assert message in capsys.readouterr().err


def test_ellipsoid_method_and_its_constrained_fallback(tmp_path, capsys):
    from maglog.sim import sentences
    flight = make_flight(coverage="full", seconds=60, seed=8)
    log = tmp_path / "LOG00003.TXT"
    log.write_bytes(flight.log())
    out = tmp_path / "e"
    assert main(["calibrate", str(log), "--method", "ellipsoid", "--out", str(out)]) == 0
    summary = json.loads((out / "parameters.json").read_text())
    assert summary["fit"] == "algebraic" and min(summary["W_eigenvalues"]) > 0
    assert summary["rms_after_nT"] < 0.01 * summary["rms_before_nT"]
    assert "positive-definite" in (out / "report.md").read_text()
    # Samples on a hyperboloid: the algebraic quadric is none, the constrained fit is used.
    rng = np.random.default_rng(1)
    angle, height = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(-1, 1, 3000)
    radius = np.sqrt(1 + height ** 2 / 4)
    b = 30_000 * np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])
    lines = b"".join(sentences.pmag1(k, *v) + sentences.cesium(48_000.0, 1500)
                     for k, v in enumerate(b))
    odd = tmp_path / "LOG00004.TXT"
    odd.write_bytes(lines)
    assert main(["calibrate", str(odd), "--method", "ellipsoid", "--out",
                 str(tmp_path / "h")]) == 0
    summary = json.loads((tmp_path / "h" / "parameters.json").read_text())
    assert summary["fit"] == "constrained"
    assert any("constrained" in w for w in summary["warnings"])
