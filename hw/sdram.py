"""SDR SDRAM controller: initialisation, auto refresh, open-row page accesses."""

from amaranth import *
from amaranth.lib import data, enum, stream, wiring
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .arch import sdram as arch
from .arch.units import hertz


__all__ = ["SdramController", "sdram_pins_signature", "request_layout"]


def request_layout(geometry):
    """A word access: read or write one word at a word address (bank, row, column)."""
    return data.StructLayout({
        "write": 1,
        "addr":  geometry.word_address_bits,
        "data":  geometry.data_width,
        "mask":  geometry.data_width // 8,     # bytes to write (1 = write that byte)
    })


def sdram_pins_signature(geometry):
    """The chip's pins, as DESIGN.md names them (``sdram_*`` at the top level)."""
    return wiring.Signature({
        "a":     Out(geometry.address_bits),
        "ba":    Out(geometry.bank_bits),
        "cs_n":  Out(1, init=1),
        "ras_n": Out(1, init=1),
        "cas_n": Out(1, init=1),
        "we_n":  Out(1, init=1),
        "cke":   Out(1),
        "dqm":   Out(geometry.data_width // 8, init=(1 << geometry.data_width // 8) - 1),
        "dq_o":  Out(geometry.data_width),
        "dq_oe": Out(1),
        "dq_i":  In(geometry.data_width),
    })


def count_up(m, counter, event, *, split=None):
    """Adds one to ``counter`` in the clock ``event`` is high, with a short carry: the high
    half counts when the low half is all ones, which a register keeps track of (so the
    low half's compare is not in the high half's path). ``counter`` is reset to zero only
    by the domain's reset."""
    width = len(counter)
    split = width // 2 if split is None else split
    low, high = counter[:split], counter[split:]
    low_ones = Signal()                 # the low half is all ones
    with m.If(event):
        m.d.sync += [low.eq(low + 1), low_ones.eq(low == (1 << split) - 2)]
        with m.If(low_ones):
            m.d.sync += high.eq(high + 1)


class _State(enum.Enum, shape=4):
    POWER_UP   = 0
    INIT_PRE   = 1
    INIT_REF   = 2
    INIT_MODE  = 3
    IDLE       = 4
    REFRESH    = 5
    PRECHARGE  = 6
    ACTIVATE   = 7
    WAIT       = 8


class SdramController(wiring.Component):
    """An SDR SDRAM controller for one chip.

    Word requests come in on ``i`` (read or write, with a byte mask for writes); read data
    leaves on ``o`` in request order, a fixed number of cycles later, with no backpressure
    (a requester asks only for what it has room for). Rows stay open per bank (page
    accesses): requests to an open row go out one a clock, so sequential traffic runs at up
    to one word per clock; another row in the bank costs a precharge and an activate. Auto
    refresh keeps its interval: when due, the controller finishes the current access,
    precharges all banks and refreshes. Every wait is counted in clocks from the chip's
    timing at ``clk_freq``; the burst length is 1 and the CAS latency 2 or 3.

    Address: ``addr`` = {row, bank, column} (column lowest), so a sequential stream walks a
    row of one bank, then the same row of the next bank.

    Members
    -------
    i : ``In(stream.Signature(request_layout(geometry)))``
    o : ``Out(stream.Signature(data_width))`` (no backpressure: ``ready`` is ignored)
    pins : ``Out(sdram_pins_signature(geometry))``
    ready : ``Out(1)``
        Initialisation is done.
    refreshes : ``Out(32)``
        Auto refreshes issued (for tests and status).
    """
    def __init__(self, chip, *, clk_freq, cas_latency=2):
        if not isinstance(chip, arch.Chip):
            raise TypeError(f"Chip must be an arch.sdram.Chip, not {chip!r}")
        if cas_latency not in (2, 3):
            raise ValueError(f"CAS latency must be 2 or 3, not {cas_latency!r}")
        if not clk_freq > 0:
            raise ValueError(f"Clock frequency must be positive, not {clk_freq!r}")
        self.chip = chip
        self.clk_freq = clk_freq
        self.cas_latency = cas_latency
        g = chip.geometry
        super().__init__({
            "i":         In(stream.Signature(request_layout(g))),
            "o":         Out(stream.Signature(g.data_width)),
            "pins":      Out(sdram_pins_signature(g)),
            "ready":     Out(1),
            "refreshes": Out(32),
        })

    def elaborate(self, platform):
        m = Module()
        chip, g, t = self.chip, self.chip.geometry, self.chip.timing
        clocks = lambda ns: t.clocks(ns, self.clk_freq)
        t_rcd, t_rp, t_ras, t_rc = clocks(t.t_rcd), clocks(t.t_rp), clocks(t.t_ras), clocks(t.t_rc)
        t_rfc, t_wr, t_mrd = clocks(t.t_rfc), clocks(t.t_wr), t.t_mrd_clocks
        power_up = clocks(t.power_up_us * 1e3)
        interval = chip.refresh_interval_clocks(self.clk_freq)
        # Refresh a little early: the request in progress and the precharge come first.
        refresh_every = interval - (t_rp + t_rc + t_wr + 8)
        if refresh_every <= 0:
            raise ValueError(f"A {hertz(self.clk_freq)} clock is too slow to refresh "
                             f"{chip.name} in time")

        pins = self.pins
        cmd = Signal(3, init=arch.Command.NOP)
        m.d.comb += [pins.ras_n.eq(cmd[2]), pins.cas_n.eq(cmd[1]), pins.we_n.eq(cmd[0])]
        next_cmd = Signal(3)
        m.d.comb += next_cmd.eq(arch.Command.NOP)
        m.d.sync += [cmd.eq(next_cmd), pins.cs_n.eq(0)]
        # Address, bank and write data. They mean something only with a command, but they
        # keep their reset: a register that holds its value and has no reset is X in Icarus
        # (its hold is computed before its initial value is set), and the chip model there
        # reads every pin at every edge.
        a = Signal(g.address_bits)
        ba = Signal(g.bank_bits)
        dq_o = Signal(g.data_width)
        m.d.comb += [pins.a.eq(a), pins.ba.eq(ba), pins.dq_o.eq(dq_o)]

        # Address fields of the request.
        req = self.i.payload
        column = req.addr[:g.column_bits]
        bank = req.addr[g.column_bits:g.column_bits + g.bank_bits]
        row = req.addr[g.column_bits + g.bank_bits:]

        # Per-bank open row (meaningful only while its `open_` bit is set, so without reset).
        open_ = Signal(g.banks)
        open_row = Array(Signal(g.row_bits, name=f"open_row{b}", reset_less=True)
                         for b in range(g.banks))
        # Clocks since the last ACTIVE, WRITE and PRECHARGE to any bank (saturating): each
        # rule is kept for every bank at once, which is never sooner than per bank (and
        # covers tRRD between banks as well).
        limit = max(t_ras, t_rc, t_wr, t_rp)
        since_act = Signal(range(limit + 1), init=limit)
        since_wr = Signal(range(limit + 1), init=limit)
        since_pre = Signal(range(limit + 1), init=limit)
        for timer in (since_act, since_wr, since_pre):
            with m.If(timer != limit):
                m.d.sync += timer.eq(timer + 1)

        # A write must not drive DQ while the chip still drives data for an earlier read.
        turnaround = self.cas_latency + 1
        since_read = Signal(range(turnaround + 1), init=turnaround)
        with m.If(since_read != turnaround):
            m.d.sync += since_read.eq(since_read + 1)

        # Refresh timer: a tick every `refresh_every` + 1 clocks (it also times power-up).
        refresh_count = Signal(range(refresh_every + 1))
        refresh_tick = Signal()
        refresh_due = Signal()
        m.d.comb += refresh_tick.eq(refresh_count == refresh_every)
        m.d.sync += refresh_count.eq(refresh_count + 1)
        with m.If(refresh_tick):
            m.d.sync += [refresh_count.eq(0), refresh_due.eq(1)]
        # Power-up: whole refresh periods that cover it (the first tick is a whole period
        # after reset).
        power_up_ticks = -(-power_up // (refresh_every + 1))

        # Read data returns CAS latency clocks after the chip sees the READ, which is one
        # clock after it is decided here; it is sampled into a register, one more.
        latency = self.cas_latency + 2
        read_pipe = Signal(latency)
        dq_in = Signal(g.data_width, reset_less=True)
        m.d.sync += [dq_in.eq(pins.dq_i), read_pipe.eq(Cat(C(0, 1), read_pipe[:-1]))]
        m.d.comb += [self.o.valid.eq(read_pipe[-1]), self.o.payload.eq(dq_in)]

        wait = Signal(range(max(t_rfc, t_rp, t_rcd, t_mrd, t_rc, t_ras) + 1))
        after_wait = Signal(_State)
        init_count = Signal(range(max(t.init_refreshes, power_up_ticks) + 1))
        state = Signal(_State)
        m.d.comb += self.ready.eq(state.as_value() >= _State.IDLE.value)

        def command(c, *, ba_=None, a_=None):
            m.d.comb += next_cmd.eq(c)
            if ba_ is not None:
                m.d.sync += ba.eq(ba_)
            if a_ is not None:
                m.d.sync += a.eq(a_)

        def wait_then(clocks_, then):
            # `clocks_` clocks from this command to the next (the command's own included).
            # The count and the next state are loaded in every clock of the state (they
            # matter only once it goes to WAIT), so that their loads do not depend on the
            # conditions of its command.
            m.d.sync += [wait.eq(clocks_ - 1), after_wait.as_value().eq(then)]

        def go_wait():
            m.d.sync += state.eq(_State.WAIT)

        # Auto refreshes are counted a clock after they are issued.
        refreshed = Signal()
        m.d.sync += refreshed.eq(0)
        count_up(m, self.refreshes, refreshed)

        # DQM masks write data at once and read data two clocks later: low except for the
        # bytes a write leaves alone (high during initialisation, as the data sheets ask).
        m.d.sync += [pins.dq_oe.eq(0), pins.dqm.eq(Mux(self.ready, 0, -1))]

        with m.Switch(state):
            with m.Case(_State.POWER_UP):
                # Waits with CKE high and NOPs for the power-up time.
                m.d.sync += pins.cke.eq(1)
                with m.If(refresh_tick):
                    m.d.sync += init_count.eq(init_count + 1)
                    with m.If(init_count == power_up_ticks - 1):
                        m.d.sync += [init_count.eq(0), state.eq(_State.INIT_PRE)]

            with m.Case(_State.INIT_PRE):
                # Precharges all banks.
                command(arch.Command.PRECHARGE, a_=1 << arch.A10)
                wait_then(t_rp, _State.INIT_REF)
                go_wait()

            with m.Case(_State.INIT_REF):
                # Issues the initialisation's auto refreshes.
                command(arch.Command.REFRESH)
                m.d.sync += init_count.eq(init_count + 1)
                wait_then(t_rfc, Mux(init_count == t.init_refreshes - 1,
                                     _State.INIT_MODE, _State.INIT_REF))
                go_wait()

            with m.Case(_State.INIT_MODE):
                # Loads the mode register: burst length 1, CAS latency.
                command(arch.Command.LOAD_MODE, ba_=0,
                        a_=arch.mode_register(cas_latency=self.cas_latency))
                wait_then(t_mrd, _State.IDLE)
                go_wait()

            with m.Case(_State.IDLE):
                # Serves a request, or refreshes when due.
                with m.If(refresh_due):
                    with m.If(open_.any()):
                        m.d.sync += state.eq(_State.PRECHARGE)
                    with m.Else():
                        m.d.sync += state.eq(_State.REFRESH)
                with m.Elif(self.i.valid):
                    bank_open = open_.bit_select(bank, 1)
                    # Every bank's row compared at once, then the request's bank picked.
                    row_open = Array(open_[b] & (open_row[b] == row)
                                     for b in range(g.banks))[bank]
                    with m.If(row_open & (~req.write | (since_read == turnaround))):
                        # The row is open: the access goes out now.
                        m.d.comb += self.i.ready.eq(1)
                        m.d.sync += [ba.eq(bank), a.eq(column)]
                        with m.If(req.write):
                            m.d.comb += next_cmd.eq(arch.Command.WRITE)
                            m.d.sync += [dq_o.eq(req.data), pins.dq_oe.eq(1),
                                         pins.dqm.eq(~req.mask), since_wr.eq(0)]
                        with m.Else():
                            m.d.comb += next_cmd.eq(arch.Command.READ)
                            m.d.sync += [read_pipe[0].eq(1), since_read.eq(0)]
                    with m.Elif(row_open):
                        pass                    # a write waits for the read data to pass
                    with m.Elif(bank_open):
                        m.d.sync += state.eq(_State.PRECHARGE)
                    with m.Else():
                        m.d.sync += state.eq(_State.ACTIVATE)

            with m.Case(_State.PRECHARGE):
                # Closes rows: all banks for a refresh, else the requested bank; waits for
                # tRAS since the last ACTIVE and tWR since the last write.
                wait_then(t_rp, Mux(refresh_due, _State.REFRESH, _State.ACTIVATE))
                with m.If((since_act >= t_ras) & (since_wr >= t_wr)):
                    go_wait()
                    m.d.sync += since_pre.eq(0)
                    with m.If(refresh_due):
                        command(arch.Command.PRECHARGE, a_=1 << arch.A10)
                        m.d.sync += open_.eq(0)
                    with m.Else():
                        command(arch.Command.PRECHARGE, ba_=bank, a_=0)
                        m.d.sync += open_.bit_select(bank, 1).eq(0)

            with m.Case(_State.REFRESH):
                # Refreshes (all banks are closed).
                command(arch.Command.REFRESH)
                m.d.sync += [refresh_due.eq(0), refreshed.eq(1)]
                wait_then(t_rfc, _State.IDLE)
                go_wait()

            with m.Case(_State.ACTIVATE):
                # Opens the requested row, once tRC since the last ACTIVE and tRP since the
                # last PRECHARGE have passed.
                wait_then(t_rcd, _State.IDLE)
                with m.If(refresh_due):
                    m.d.sync += state.eq(_State.IDLE)
                with m.Elif((since_act >= t_rc) & (since_pre >= t_rp)):
                    command(arch.Command.ACTIVE, ba_=bank, a_=row)
                    m.d.sync += [open_.bit_select(bank, 1).eq(1), open_row[bank].eq(row),
                                 since_act.eq(0)]
                    go_wait()

            with m.Case(_State.WAIT):
                # Counts down a command's timing (NOPs meanwhile).
                with m.If(wait == 0):
                    m.d.sync += state.eq(after_wait)
                with m.Else():
                    m.d.sync += wait.eq(wait - 1)

        return m
