"""What `maglog run` prints at its head names both seeds (the scenario's own, from its
TOML, and --seed, the PSO's and papers'), and no line of the summary reads like a Python
value (a dict's braces, None, a clock in exponent form)."""

import re

from maglog.calib.card import read_logs
from maglog.cli.summary import summarize


def test_the_title_names_both_seeds(flown):
    _, _, image, truth, run, counters = flown
    assert truth["seed"] == 5
    text = summarize(truth, counters, read_logs(image), run, seed=7).text
    title = text.splitlines()[0]
    assert title == ("maglog run: scenario test (scenario seed 5), PSO and papers' seed 7 "
                     "(--seed)")
    assert text.splitlines()[1] == "=" * len(title)
    bare = summarize(truth, counters, read_logs(image), run).text.splitlines()[0]
    assert bare == "maglog run: scenario test (scenario seed 5)"


def test_no_line_reads_like_a_python_value(flown):
    _, _, image, truth, run, counters = flown
    text = summarize(truth, counters, read_logs(image), run, seed=0).text
    for line in text.splitlines():
        assert not re.search(r"[{}]|\bNone\b|\de\+0", line), line
