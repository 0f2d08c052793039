"""Every example in README.md and docs/*.md, run as written.

The examples are taken out of the Markdown itself: every fenced block marked ``sh``,
``python``, ``c`` or ``toml``. A shell block's commands (one per line, ``\\`` continuations
joined, ``#`` comments dropped) each go to the first rule of :data:`RULES` whose pattern
matches; a command no rule claims fails :func:`test_every_example_is_claimed`, so a new
example cannot land without a test. A rule either runs the command verbatim from a scratch
folder (``.venv`` there is a link to this environment's, so ``.venv/bin/maglog`` is the
installed maglog; ``build/`` and every other relative path are the scratch folder's), after
putting in place the inputs the example names (a run's folder, a scenario file, a serial
port: a pseudo-terminal's name takes the place of ``/dev/ttyUSBn``), or says which CI step
runs it (``make test`` and ``make run`` are the CI's own steps; the pip commands are
``make test-wheel``'s). Python blocks run with the scratch folder as the working directory;
the C block is compiled against the header the component example writes; TOML blocks are
loaded as scenarios.

A command passes when it exits 0 (or, for a rule that expects it, with the one-line error a
user without the hardware gets) and its outputs exist. Printed outputs shown in the Markdown
are checked where they are: the end of ``make run`` by the slow main-job test below.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
VENV_BIN = Path(sys.executable).parent
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LANGUAGES = ("sh", "python", "c", "toml")


@dataclass(frozen=True)
class Example:
    """One example: a shell command, or a whole Python, C or TOML block."""
    document: str          # path relative to the repository
    line: int              # line of the command (or the block's first line)
    language: str
    text: str

    @property
    def id(self):
        return f"{self.document}:{self.line}"


def _blocks(path):
    text = path.read_text(encoding="utf-8")
    for match in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
        yield text[:match.start(2)].count("\n") + 1, match.group(1), match.group(2)


def _commands(first_line, body):
    """(line, command) for each command of a shell block."""
    pending, start = "", None
    for offset, raw in enumerate(body.splitlines()):
        line = raw.rstrip()
        if start is None:
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            start = first_line + offset
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        pending += re.sub(r"\s+#.*$", "", line)
        yield start, " ".join(pending.split())
        pending, start = "", None
    assert start is None, f"a continuation line ends the block at line {first_line}"


def examples():
    found = []
    for path in DOCUMENTS:
        name = str(path.relative_to(ROOT))
        for line, language, body in _blocks(path):
            if language == "sh":
                found += [Example(name, at, "sh", command)
                          for at, command in _commands(line, body)]
            elif language in LANGUAGES:
                found.append(Example(name, line, language, body))
    return found


EXAMPLES = examples()


# --- what each example needs, and how it runs --------------------------------------------

@dataclass
class Rule:
    """Claims the examples whose text matches ``pattern`` (a regular expression searched
    in a shell command, or in a whole block of another language)."""
    pattern: str
    how: str                        # "run", or the CI step that runs it
    language: str = "sh"
    slow: bool = False
    needs: tuple = ()               # inputs put in place first (see Scratch.provide)
    ports: int = 0                  # /dev/ttyUSB0.. replaced by pseudo-terminals
    outputs: tuple = ()             # paths the command must leave behind
    timeout: float = 300.0
    #: (tool, message): without ``tool`` on PATH the example must end in exit status 1 and
    #: this one-line message (a user without that tool meets it), not a shell's error.
    without: tuple = ()

    def claims(self, example):
        return example.language == self.language and re.search(self.pattern, example.text)


MAGLOG = r"^\.venv/bin/maglog "

RULES = [
    # The CI's own steps (.ci/run): the README's two commands, and the plain pip install.
    Rule(r"^make (run|test)$", "ci: .ci/run"),
    Rule(r"^python3(\.\d+)? -m venv venv && venv/bin/pip install \.$", "ci: make test-wheel"),
    Rule(r"^venv/bin/pip install '?\.\[(sim|synth)\]'?$", "ci: make test-wheel"),
    # The gateware.
    Rule(MAGLOG + r"hdl verilog .*--frontend", "run", outputs=("build/maglog_frontend.v",)),
    Rule(MAGLOG + r"hdl verilog ", "run", slow=True, timeout=600),
    Rule(MAGLOG + r"hdl regmap .*-o docs/registers\.md", "run", needs=("docs",),
         outputs=("docs/registers.md",)),
    Rule(MAGLOG + r"hdl regmap ", "run", outputs=("build/maglog_regs.h",)),
    Rule(MAGLOG + r"hdl resources", "run", slow=True, timeout=900),
    Rule(MAGLOG + r"hdl build ", "run", needs=("build/ep4ce6",), timeout=600),
    Rule(MAGLOG + r"hdl component ", "run", timeout=600),
    Rule(r"^maglog hdl (build|component) ", "run", timeout=600),
    Rule(r"^cd build/de0nano && \./build\.sh$", "run", needs=("de0nano project",),
         without=("quartus_sh", r"^build\.sh: Quartus Prime with Platform Designer is not "
                                r"on PATH \(not found: .*quartus_sh\); add its bin")),
    # Cards, calibration, the survey.
    Rule(MAGLOG + r"card format ", "run"),
    Rule(MAGLOG + r"card ", "run"),
    Rule(MAGLOG + r"calibrate LOG00001\.TXT", "run", needs=("LOG00001.TXT",)),
    Rule(MAGLOG + r"calibrate ", "run", timeout=600),
    Rule(MAGLOG + r"simulate survey ", "run", slow=True, outputs=("build/survey/card.img",)),
    Rule(r"^\.venv/bin/dask (scheduler|worker) .*&$",
         "the --scheduler example's test, which starts it as written"),
    Rule(MAGLOG + r"survey .*--scheduler", "run", slow=True, needs=("scheduler",),
         timeout=900),
    Rule(MAGLOG + r"survey ", "run", slow=True, timeout=900),
    # Whole runs.
    Rule(MAGLOG + r"run --backend model ", "run"),
    Rule(MAGLOG + r"run$", "ci: .ci/run (make run)"),
    Rule(MAGLOG + r"run ", "run", slow=True, needs=("my_flight.toml",), timeout=900),
    Rule(MAGLOG + r"simulate .*--backend model", "run"),
    Rule(MAGLOG + r"simulate ", "run", slow=True, timeout=900),
    Rule(MAGLOG + r"demo ", "run", slow=True, timeout=900),
    # Hardware in the loop, over pseudo-terminals.
    Rule(MAGLOG + r"replay ", "run", slow=True, needs=("my_flight.toml",), ports=3,
         timeout=300),
    Rule(MAGLOG + r"record ", "run", ports=3, timeout=120),
    # Blocks of other languages.
    Rule(r"load_scenario", "run", language="python", needs=("my.toml",)),
    Rule(r"IORD_32DIRECT", "run", language="c"),
    Rule(r"^\[", "run", language="toml"),
]


def rule_for(example):
    for rule in RULES:
        if rule.claims(example):
            return rule
    return None


def test_every_example_is_claimed():
    assert EXAMPLES, "no examples found: the Markdown parser is broken"
    unclaimed = [f"{e.id}: {e.text.splitlines()[0]}" for e in EXAMPLES if rule_for(e) is None]
    assert not unclaimed, "examples no test runs:\n" + "\n".join(unclaimed)


def test_ci_steps_named_by_rules_exist():
    """The examples said to be run by CI are in the scripts CI runs."""
    ci = (ROOT / ".ci" / "run").read_text()
    wheel = (ROOT / "scripts" / "wheel_check.sh").read_text()
    assert re.search(r"^make test$", ci, re.M) and re.search(r"^make run$", ci, re.M)
    assert re.search(r"^make test-wheel$", ci, re.M)
    assert "pip install" in wheel and "maglog" in wheel
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^run: setup\n\t.*maglog run$", makefile, re.M)


def _param(example):
    rule = rule_for(example)
    marks = []
    if rule is None or not rule.how == "run":
        marks.append(pytest.mark.skip(reason=f"run by {rule.how}" if rule else "unclaimed"))
    elif rule.slow:
        marks.append(pytest.mark.slow)
    return pytest.param(example, id=example.id, marks=marks)


# --- the scratch folder -------------------------------------------------------------------

class Scratch:
    """A folder to run examples from, with ``.venv`` linking to this environment."""

    def __init__(self, folder, shared):
        self.folder = folder
        self.shared = shared
        (folder / ".venv").mkdir()
        (folder / ".venv" / "bin").symlink_to(VENV_BIN)
        self.background = []
        self.env = dict(os.environ, PATH=f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}",
                        MAGLOG_BUILD_DIR=str(shared.build_dir))

    #: Inputs an example may name, made from the session's shared run and survey; a path
    #: is provided when a command names it other than as its ``-o``/``--out``.
    INPUTS = ("build/logs/LOG00001.TXT", "build/survey/logs/LOG00001.TXT", "build/run",
              "build/quick", "build/survey")

    def provide_for(self, command):
        for need in self.INPUTS:
            pattern = rf"(?<![\w/.-]){re.escape(need)}(?![\w.-])"
            mentions = [m.start() for m in re.finditer(pattern, command)]
            if any(not re.search(r"(-o|--out|--output) $", command[:at]) for at in mentions):
                self.provide(need)

    def provide(self, need):
        target = self.folder / need
        if need.startswith("build/survey/"):
            self.provide("build/survey")        # the folder first: its files linked in
        if target.exists():
            return
        target.parent.mkdir(parents=True, exist_ok=True)
        if need == "docs":
            target.mkdir()
        elif need == "my.toml":
            target.write_text((ROOT / "sim/stimulus/short.toml").read_text())
        elif need == "my_flight.toml":
            # A flight of one's own: the default's, renamed (a shorter one would leave its
            # faults' windows or its parameters undetermined, and could not pass).
            text = (ROOT / "sim/stimulus/default.toml").read_text()
            text, count = re.subn(r'(?m)^name = "default"', 'name = "my_flight"', text)
            assert count == 1, "default.toml's [scenario] name moved"
            target.write_text(text)
        elif need in ("build/run", "build/quick", "build/survey"):
            # The shared folder's files linked into a folder of this scratch's own, so that
            # an example may write beside them.
            source = self.shared.survey() if need == "build/survey" else self.shared.run()
            target.mkdir()
            for item in source.iterdir():
                (target / item.name).symlink_to(item)
        elif need in ("LOG00001.TXT", "build/logs/LOG00001.TXT"):
            target.write_bytes(self.shared.log(self.shared.run()))
        elif need == "build/survey/logs/LOG00001.TXT":
            target.write_bytes(self.shared.log(self.shared.survey()))
        elif need in ("build/ep4ce6", "build/de0nano"):
            target.mkdir()
            (target / "left-over.txt").write_text("not empty: --force is needed\n")
        elif need == "de0nano project":
            result = self.run(".venv/bin/maglog hdl build --board de0nano -o build/de0nano",
                              600)
            assert result.returncode == 0, result.stderr
        elif need == "scheduler":
            self._start_cluster()
        else:
            raise AssertionError(f"unknown input {need}")

    def _start_cluster(self):
        """The README's own commands that start a Dask scheduler and worker (the lines of
        the --scheduler example's block that end in ``&``), run as written; stopped by
        :meth:`close`."""
        import socket
        lines = [e.text for e in EXAMPLES if re.match(r"^\.venv/bin/dask .*&$", e.text)]
        assert any(" scheduler " in f"{line} " for line in lines), "no scheduler command"
        for line in lines:
            self.background.append(subprocess.Popen(
                ["bash", "-c", "exec " + line.rstrip("&").strip()], cwd=self.folder,
                env=self.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            if " scheduler " in f"{line} ":
                port = int(re.search(r"--port (\d+)", line).group(1))
                deadline = time.monotonic() + 60
                while True:
                    try:
                        socket.create_connection(("127.0.0.1", port), 1).close()
                        break
                    except OSError:
                        assert time.monotonic() < deadline, "the scheduler did not start"
                        time.sleep(0.5)
        time.sleep(3)                       # the worker registers

    def close(self):
        for process in self.background:
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()

    def run(self, command, timeout, env=None):
        return subprocess.run(["bash", "-c", command], cwd=self.folder,
                              env=env or self.env, capture_output=True, text=True,
                              timeout=timeout)


class Shared:
    """Inputs several examples take, made once per session from maglog itself."""

    def __init__(self, folder):
        self.folder = folder
        self.build_dir = folder / "sim-build"
        self._run = self._survey = None

    def _maglog(self, *args, timeout=900):
        result = subprocess.run([str(VENV_BIN / "maglog"), *args], cwd=self.folder,
                                capture_output=True, text=True, timeout=timeout)
        assert result.returncode == 0, (args, result.stdout[-2000:], result.stderr[-2000:])
        return result.stdout

    def run(self):
        """A run's folder (``maglog run -o``) from the model backend: card.img, attitude.csv,
        truth.json, report/."""
        if self._run is None:
            self.run_printed = self._maglog("run", "--backend", "model", "--quick-papers",
                                            "--quiet", "-o", "run")
            self._run = self.folder / "run"
        return self._run

    @staticmethod
    def log(folder):
        from maglog.calib.card import read_logs
        return read_logs(folder / "card.img")[-1][1]

    def survey(self):
        if self._survey is None:
            self._maglog("simulate", "survey", "--backend", "model", "--quiet",
                         "-o", "survey/card.img")
            self._survey = self.folder / "survey"
        return self._survey


@pytest.fixture(scope="session")
def shared(tmp_path_factory):
    return Shared(tmp_path_factory.mktemp("examples-shared"))


@pytest.fixture
def scratch(tmp_path, shared):
    folder = Scratch(tmp_path, shared)
    yield folder
    folder.close()


def test_readme_verdicts_are_what_the_default_scenario_prints(shared):
    """The README's end of ``make run`` against the default scenario on the model backend,
    which gives the RTL's card block for block (the slow main-job test in
    tests/cli/test_run.py checks it against the RTL run itself)."""
    from readme import printed_verdicts, readme_verdicts, same_printout
    shared.run()
    difference = same_printout(readme_verdicts(), printed_verdicts(shared.run_printed))
    assert difference is None, "README.md's printed verdicts are stale:\n" + difference


def printed_blocks():
    """(document, line, command, block) for each block the Markdown marks as a command's
    output with ``<!-- printed: COMMAND -->`` on the line before it."""
    found = []
    for path in DOCUMENTS:
        text = path.read_text(encoding="utf-8")
        for match in re.finditer(r"^<!-- printed: (.+?) -->\n```\w*\n(.*?)^```", text,
                                 re.S | re.M):
            line = text[:match.start()].count("\n") + 1
            found.append(pytest.param(match.group(1), match.group(2).strip("\n"),
                                      id=f"{path.relative_to(ROOT)}:{line}"))
    return found


@pytest.mark.parametrize("command, shown", printed_blocks())
def test_printed_output_is_what_the_command_prints(command, shown, scratch):
    from readme import same_printout
    scratch.provide_for(command)
    result = scratch.run(command, 300)
    assert result.returncode == 0, result.stderr
    difference = same_printout(shown, result.stdout.strip("\n"))
    assert difference is None, f"`{command}` prints otherwise now:\n{difference}"


# --- the tests ----------------------------------------------------------------------------

@pytest.mark.parametrize("example", [_param(e) for e in EXAMPLES if e.language == "sh"])
def test_shell_example(example, scratch):
    rule = rule_for(example)
    for need in rule.needs:
        scratch.provide(need)
    command = example.text
    scratch.provide_for(command)
    if rule.ports:
        _run_with_ports(example, rule, scratch)
        return
    result = scratch.run(command, rule.timeout)
    if rule.without and shutil.which(rule.without[0], path=scratch.env["PATH"]) is None:
        tool, message = rule.without
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 1 and len(lines) == 1 and re.match(message, lines[0]), (
            f"{example.id}: without {tool}: exit {result.returncode}, {result.stderr}")
        return
    assert result.returncode == 0, (
        f"{example.id}: `{command}` exited {result.returncode}\n"
        f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    for output in rule.outputs:
        assert (scratch.folder / output).exists(), f"{example.id}: no {output}"
    assert "Traceback" not in result.stderr, result.stderr[-3000:]


def _run_with_ports(example, rule, scratch):
    """``maglog replay`` / ``record`` with pseudo-terminals for /dev/ttyUSB0..: replay's
    bytes are read off the other ends; record is fed the short scenario's bytes, then
    stopped as its example says (Ctrl-C, or its --seconds)."""
    masters, command = [], example.text
    for n in range(rule.ports):
        master, slave = os.openpty()
        masters.append(master)
        command = command.replace(f"/dev/ttyUSB{n}", os.ttyname(slave))
        os.set_blocking(master, False)
    received = [bytearray() for _ in masters]
    done = threading.Event()

    def drain():
        while not done.is_set():
            for k, master in enumerate(masters):
                try:
                    received[k] += os.read(master, 65536)
                except (BlockingIOError, OSError):
                    pass
            time.sleep(0.005)
    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    process = subprocess.Popen(["bash", "-c", f"exec {command}"], cwd=scratch.folder,
                               env=scratch.env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        if " record " in f" {example.text} ":
            _feed_short(masters)
            seconds = re.search(r"--seconds (\S+)", example.text)
            if seconds is None:
                time.sleep(1.0)
                process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=rule.timeout)
    finally:
        done.set()
        reader.join()
        if process.poll() is None:
            process.kill()
        for master in masters:
            os.close(master)
    assert process.returncode == 0, f"{example.id}: exit {process.returncode}\n{out}\n{err}"
    assert "Traceback" not in err, err
    if " replay " in f" {example.text} ":
        named = re.findall(r"--port (?:\w+=)?/dev/ttyUSB(\d)", example.text)
        for n in named:
            assert len(received[int(n)]) > 1000, f"{example.id}: /dev/ttyUSB{n} got nothing"
    else:
        output = scratch.folder / re.search(r"-o (\S+)", example.text).group(1)
        assert output.stat().st_size > 1000, f"{example.id}: {output} is nearly empty"


def _feed_short(masters):
    """The short scenario's bytes, channel k on port k, each channel's in time order."""
    from maglog.sim.stimulus import load_scenario
    system = load_scenario("short").build().system
    for k, master in enumerate(masters[:len(system.channels)]):
        data = system.channel_bytes(k)
        while data:
            try:
                data = data[os.write(master, data[:4096]):]
            except BlockingIOError:
                time.sleep(0.01)       # the reader has not caught up


@pytest.mark.parametrize("example", [_param(e) for e in EXAMPLES if e.language == "python"])
def test_python_example(example, scratch):
    rule = rule_for(example)
    for need in rule.needs:
        scratch.provide(need)
    script = scratch.folder / "example.py"
    script.write_text(example.text)
    result = subprocess.run([sys.executable, str(script)], cwd=scratch.folder,
                            env=scratch.env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{example.id}\n{result.stderr[-3000:]}"


@pytest.mark.parametrize("example", [_param(e) for e in EXAMPLES if e.language == "c"])
def test_c_example(example, scratch, external):
    """The C block compiles against the header ``maglog hdl component`` writes, with the
    two HAL macros it uses (io.h) and the base address Platform Designer puts in system.h."""
    cc = external.tool("gcc", "the C example is compiled")
    component = scratch.folder / "component"
    result = scratch.run(f".venv/bin/maglog hdl component -o {component}", 600)
    assert result.returncode == 0, result.stderr
    (scratch.folder / "io.h").write_text(
        "#include <stdint.h>\n"
        "#define IORD_32DIRECT(base, off) (*(volatile uint32_t *)((base) + (off)))\n"
        "#define IOWR_32DIRECT(base, off, v) (*(volatile uint32_t *)((base) + (off)) = (v))\n")
    (scratch.folder / "system.h").write_text("#define MAGLOG_0_BASE 0x00010000u\n")
    body = "\n".join(line for line in example.text.splitlines()
                     if not line.startswith("#include"))
    includes = "\n".join(line for line in example.text.splitlines()
                         if line.startswith("#include"))
    (scratch.folder / "example.c").write_text(
        f"#include <stdint.h>\n{includes}\nvoid fail(const char *why);\n"
        f"uint32_t example(void) {{\n{body}\nreturn status;\n}}\n")
    result = subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-c", "example.c",
                             "-I", ".", "-I", str(component), "-o", "example.o"],
                            cwd=scratch.folder, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("example", [_param(e) for e in EXAMPLES if e.language == "toml"])
def test_toml_example(example, scratch, external):
    """A TOML block is a valid scenario fragment: loaded over the defaults and built."""
    from maglog.sim.stimulus import load_scenario
    if "shared:" in example.text:
        external.shared_data()
    path = scratch.folder / "fragment.toml"
    path.write_text(example.text)
    scenario = load_scenario(str(path))
    assert scenario is not None


def test_links_stay_in_the_repository():
    """Every relative link of the Markdown names a file of the repository (anchors and web
    addresses aside): a reader with only the repository can follow each one."""
    broken = []
    for path in DOCUMENTS:
        text = path.read_text(encoding="utf-8")
        for match in re.finditer(r"\]\(([^)\s]+)\)", text):
            target = match.group(1).split("#")[0]
            if not target or re.match(r"^[a-z]+:", target):
                continue
            resolved = (path.parent / target).resolve()
            line = text[:match.start()].count("\n") + 1
            if ROOT not in resolved.parents or not resolved.exists():
                broken.append(f"{path.relative_to(ROOT)}:{line}: {match.group(1)}")
    assert not broken, "links that leave the repository or lead nowhere:\n" + "\n".join(broken)
