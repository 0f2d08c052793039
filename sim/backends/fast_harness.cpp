// The fast system harness: the logger's Verilog (Verilator), with every device front that
// runs per clock written here in C++, loaded into Python with ctypes.
//
// Python stays at frame, command and block granularity:
//   * UART lines: Python queues bytes with their start cycle and bit time per channel; the
//     transmitters here turn them into line levels (8N1, LSB first, idle high).
//   * SD card: the front here deserialises commands and data blocks from the SD pins and
//     serialises responses, CRC status tokens, busy and read blocks. What the card *does*
//     is decided in Python by the command-level card model (sim/models/logger_sd.ModelCard),
//     called back once per command, once per received block and once when a block's
//     programming ends.
//   * SDRAM: a functional chip (mode register, open rows, reads after the CAS latency,
//     byte masks) entirely here: the ring's data never crosses into Python.
//   * Wishbone: one call per register access (the firmware's bus), run to its ack here.
//
// The Verilog top is `maglog_fast` (written by sim/backends/fast.py): it registers every
// input of `maglog_logger` on the rising edge and holds the logger in reset for a few
// clocks after power-up, so that no logic depends combinationally on a top-level input
// and the falling-edge evaluation costs nothing.
//
// Clocking: each cycle is "clk = 1, eval" then "inputs, clk = 0, eval". After the rising
// edge of cycle k, the outputs read here are the values the next edge samples; inputs set
// here reach the logger through its input registers at edge k + 1, and are sampled by it at
// edge k + 2.

#include "Vmaglog_fast.h"
#include "verilated.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <deque>
#include <string>
#include <vector>

namespace {

typedef int (*command_cb)(uint64_t bits);
typedef int (*block_cb)(const uint8_t* data, int crc_ok);
typedef int (*event_cb)(void);

struct UartByte {
    int64_t start;          // cycle of the start bit's leading edge
    double bit_cycles;      // clock cycles per bit on this byte's line
    uint8_t value;
    uint8_t stop;           // level of the stop bit (0: a framing error)
};

struct UartLine {
    std::deque<UartByte> queue;
    int level = 1;
    int bit = -1;           // bit of the current byte on the line (-1: idle)
    int64_t next_change = INT64_MAX;
};

// -- CRC16-CCITT (x^16 + x^12 + x^5 + 1), one per DAT line ----------------------------------
static uint16_t crc16_bit(uint16_t crc, int bit) {
    int feedback = ((crc >> 15) & 1) ^ bit;
    crc = (uint16_t)(crc << 1);
    if (feedback) crc ^= 0x1021;
    return crc;
}

enum class CmdState { Idle, Receive, Gap, Respond };
enum class DatState { Idle, Receive, TokenGap, Token, Busy, ReadWait, Send };

struct Harness {
    VerilatedContext* context;
    Vmaglog_fast* top;
    int64_t cycle = 0;              // rising edges so far
    int channels;
    std::vector<UartLine> lines;
    std::deque<std::pair<int64_t, int>> button;     // (cycle, level)
    std::vector<std::string> errors;
    bool aborted = false;

    // SDRAM
    int row_bits, col_bits, bank_bits, data_bits;
    std::vector<uint32_t> memory;
    std::vector<int> open_row;
    int cas_latency = 3;
    std::deque<std::pair<int64_t, uint32_t>> dq_due;   // (edge after which to set, value)
    uint64_t sdram_commands = 0;

    // SD card front
    command_cb on_command = nullptr;
    block_cb on_block = nullptr;
    event_cb on_programmed = nullptr;
    int sd_clk_before = 0;
    int card_cmd_oe = 0, card_cmd = 1, card_dat_oe = 0, card_dat = 0xF;
    CmdState cmd_state = CmdState::Idle;
    uint64_t cmd_bits = 0;
    int cmd_count = 0;
    std::vector<uint8_t> response;  // bits to send, first first
    size_t response_at = 0;
    int gap = 0;
    int64_t busy_after_response = 0;    // cycles of R1b busy (0: none)
    // read block to send after the response
    bool read_pending = false;
    int64_t read_delay = 0;
    std::vector<uint8_t> read_nibbles;  // start, data, CRC, end
    size_t read_at = 0;
    int64_t wait_until = 0;
    // write blocks
    bool rx_enabled = false;
    DatState dat_state = DatState::Idle;
    std::vector<uint8_t> rx_nibbles;
    int token = 0;
    std::vector<uint8_t> token_bits;
    size_t token_at = 0;
    int64_t busy_cycles = 0;
    int64_t busy_until = 0;
    bool programming = false;       // a written block's busy (on_programmed at its end)
    uint64_t sd_edges = 0, sd_commands = 0, sd_blocks = 0;

    // Wishbone
    uint64_t wb_accesses = 0;

    void error(const std::string& message) {
        if (errors.size() < 100)
            errors.push_back("cycle " + std::to_string(cycle) + ": " + message);
    }
};

// Advance a line to `cycle` (called when cycle >= next_change). A byte whose start has
// passed while the line was busy starts now, with its own bit timing.
static void uart_step(UartLine& line, int64_t cycle) {
    while (line.next_change <= cycle) {
        if (line.queue.empty()) { line.next_change = INT64_MAX; return; }
        UartByte& b = line.queue.front();
        if (line.bit == -1 && b.start < cycle) b.start = cycle;
        line.bit += 1;
        if (line.bit <= 9) {
            // 0: start, 1..8: data LSB first, 9: stop
            line.level = line.bit == 0 ? 0 : line.bit <= 8 ? (b.value >> (line.bit - 1)) & 1
                                                           : b.stop;
            line.next_change = b.start + (int64_t)(b.bit_cycles * (line.bit + 1) + 0.5);
        } else {
            // The stop bit is over: idle high until the next byte.
            line.level = 1;
            line.bit = -1;
            line.queue.pop_front();
            line.next_change = line.queue.empty() ? INT64_MAX
                                                  : std::max(line.queue.front().start, cycle);
        }
    }
}

// -- SDRAM ------------------------------------------------------------------------------------

static void sdram_edge(Harness* h) {
    Vmaglog_fast* t = h->top;
    // The pins now hold what the next rising edge (number cycle + 1) samples.
    if (!t->sdram_cke || t->sdram_cs_n) return;
    int command = (t->sdram_ras_n << 2) | (t->sdram_cas_n << 1) | t->sdram_we_n;
    if (command == 7) return;   // NOP
    h->sdram_commands++;
    int bank = t->sdram_ba;
    uint32_t a = t->sdram_a;
    int64_t edge = h->cycle + 1;
    switch (command) {
    case 0:     // LOAD MODE
        h->cas_latency = (a >> 4) & 7;
        if ((a & 7) != 0) h->error("the SDRAM front supports burst length 1 only");
        break;
    case 1: break;              // AUTO REFRESH
    case 2:                     // PRECHARGE
        if (a & (1u << 10)) for (auto& r : h->open_row) r = -1;
        else h->open_row[bank] = -1;
        break;
    case 3:                     // ACTIVE
        if (h->open_row[bank] >= 0) h->error("SDRAM ACTIVE on a bank with an open row");
        h->open_row[bank] = (int)(a & ((1u << h->row_bits) - 1));
        break;
    case 4:                     // WRITE
    case 5: {                   // READ
        int row = h->open_row[bank];
        if (row < 0) { h->error("SDRAM READ/WRITE on a bank with no open row"); break; }
        uint32_t column = a & ((1u << h->col_bits) - 1);
        size_t index = (((size_t)bank << h->row_bits | row) << h->col_bits) | column;
        if (command == 4) {
            uint32_t mask = 0;
            for (int k = 0; k < h->data_bits / 8; k++)
                if (!((t->sdram_dqm >> k) & 1)) mask |= 0xFFu << (8 * k);
            h->memory[index] = (h->memory[index] & ~mask) | (t->sdram_dq_o & mask);
            if (!t->sdram_dq_oe) h->error("SDRAM WRITE without the controller driving DQ");
        } else {
            // Sampled by the controller at edge + CL; an input set after edge k is
            // sampled at edge k + 2.
            h->dq_due.emplace_back(edge + h->cas_latency - 2, h->memory[index]);
        }
        if (a & (1u << 10)) h->open_row[bank] = -1;     // auto precharge
        break;
    }
    default: break;             // BURST TERMINATE
    }
}

// -- SD card front ---------------------------------------------------------------------------

static void sd_lines(Harness* h) {
    Vmaglog_fast* t = h->top;
    t->sd_cmd_i_in = h->card_cmd_oe ? h->card_cmd : 1;
    t->sd_dat_i_in = (h->card_dat & (h->card_dat_oe ? 0xF : 0)) | (h->card_dat_oe ? 0 : 0xF);
}

static void read_packet(Harness* h, const uint8_t* data) {
    h->read_nibbles.clear();
    h->read_nibbles.push_back(0x0);
    uint16_t crc[4] = {0, 0, 0, 0};
    for (int i = 0; i < 512; i++) {
        for (int half = 0; half < 2; half++) {
            int nibble = half == 0 ? data[i] >> 4 : data[i] & 0xF;
            h->read_nibbles.push_back((uint8_t)nibble);
            for (int line = 0; line < 4; line++) crc[line] = crc16_bit(crc[line], (nibble >> line) & 1);
        }
    }
    for (int bit = 15; bit >= 0; bit--) {
        int nibble = 0;
        for (int line = 0; line < 4; line++) nibble |= ((crc[line] >> bit) & 1) << line;
        h->read_nibbles.push_back((uint8_t)nibble);
    }
    h->read_nibbles.push_back(0xF);
    h->read_at = 0;
}

static bool check_block(const std::vector<uint8_t>& nibbles, uint8_t* data) {
    // nibbles: 1024 data, 16 CRC, 1 end (the start nibble is not kept)
    uint16_t crc[4] = {0, 0, 0, 0};
    for (int i = 0; i < 1024; i++) {
        int nibble = nibbles[i];
        for (int line = 0; line < 4; line++) crc[line] = crc16_bit(crc[line], (nibble >> line) & 1);
        if (i % 2 == 0) data[i / 2] = (uint8_t)(nibble << 4);
        else data[i / 2] |= (uint8_t)nibble;
    }
    bool ok = nibbles[1040] == 0xF;
    for (int line = 0; line < 4; line++) {
        uint16_t sent = 0;
        for (int bit = 0; bit < 16; bit++) sent = (uint16_t)(sent << 1 | ((nibbles[1024 + bit] >> line) & 1));
        if (sent != crc[line]) ok = false;
    }
    return ok;
}

// One rising edge of sd_clk: the host's levels are sampled, the card's outputs for the
// following SD clock period are set.
static void sd_edge(Harness* h) {
    Vmaglog_fast* t = h->top;
    h->sd_edges++;
    int host_cmd_oe = t->sd_cmd_oe, host_dat_oe = t->sd_dat_oe;
    int cmd = host_cmd_oe ? t->sd_cmd_o : (h->card_cmd_oe ? h->card_cmd : 1);
    int released = (h->card_dat & (h->card_dat_oe ? 0xF : 0)) | (h->card_dat_oe ? 0 : 0xF);
    int dat = host_dat_oe ? t->sd_dat_o : released;
    if (host_cmd_oe && h->card_cmd_oe) h->error("SD bus contention on CMD");
    if (host_dat_oe && h->card_dat_oe) h->error("SD bus contention on DAT");

    // CMD line
    switch (h->cmd_state) {
    case CmdState::Idle:
        h->card_cmd_oe = 0;
        if (host_cmd_oe && cmd == 0) {
            h->cmd_bits = 0;
            h->cmd_count = 1;
            h->cmd_state = CmdState::Receive;
        }
        break;
    case CmdState::Receive:
        if (!host_cmd_oe) h->error("SD host released CMD inside a command");
        h->cmd_bits = h->cmd_bits << 1 | (uint64_t)cmd;
        if (++h->cmd_count == 48) {
            h->sd_commands++;
            h->response.clear();
            h->busy_after_response = 0;
            h->cmd_state = CmdState::Idle;
            if (h->on_command(h->cmd_bits) != 0) { h->aborted = true; return; }
            // on_command called fast_sd_respond (or not: no response)
        }
        break;
    case CmdState::Gap:
        if (--h->gap <= 0) h->cmd_state = CmdState::Respond;
        h->card_cmd_oe = 0;
        if (h->cmd_state == CmdState::Respond) {
            h->card_cmd_oe = 1;
            h->card_cmd = h->response[h->response_at++];
        }
        break;
    case CmdState::Respond:
        if (h->response_at < h->response.size()) {
            h->card_cmd = h->response[h->response_at++];
        } else {
            h->card_cmd_oe = 0;
            h->cmd_state = CmdState::Idle;
            if (h->busy_after_response > 0) {
                h->dat_state = DatState::Busy;
                h->busy_until = h->cycle + h->busy_after_response;
                h->programming = false;
                h->card_dat_oe = 1;
                h->card_dat = 0xE;
            } else if (h->read_pending) {
                h->read_pending = false;
                h->dat_state = DatState::ReadWait;
                h->wait_until = h->cycle + h->read_delay;
            }
        }
        break;
    }
    if (h->aborted) return;

    // DAT lines
    switch (h->dat_state) {
    case DatState::Idle:
        h->card_dat_oe = 0;
        if (h->rx_enabled && host_dat_oe && dat == 0) {
            h->rx_nibbles.clear();
            h->dat_state = DatState::Receive;
        }
        break;
    case DatState::Receive:
        if (!h->rx_enabled) { h->dat_state = DatState::Idle; break; }    // CMD12 ended it
        h->rx_nibbles.push_back((uint8_t)dat);
        if (h->rx_nibbles.size() == 1041) {
            uint8_t data[512];
            bool ok = check_block(h->rx_nibbles, data);
            h->sd_blocks++;
            h->token = 0;
            h->dat_state = DatState::Idle;
            if (h->on_block(data, ok) != 0) { h->aborted = true; return; }
            // on_block called fast_sd_token: the token and the busy follow
        }
        break;
    case DatState::TokenGap:
        h->card_dat_oe = 0;
        if (--h->gap <= 0) {
            h->dat_state = DatState::Token;
            h->token_at = 0;
            h->card_dat_oe = 1;
            h->card_dat = 0xE | h->token_bits[h->token_at++];
        }
        break;
    case DatState::Token:
        if (h->token_at < h->token_bits.size()) {
            h->card_dat = 0xE | h->token_bits[h->token_at++];
        } else {
            h->dat_state = DatState::Busy;
            h->busy_until = h->cycle + h->busy_cycles;
            h->programming = true;
            h->card_dat = 0xE;
        }
        break;
    case DatState::Busy:
        if (h->cycle >= h->busy_until) {
            h->card_dat_oe = 0;
            h->dat_state = DatState::Idle;
            if (h->programming) {
                h->programming = false;
                if (h->on_programmed() != 0) { h->aborted = true; return; }
            }
        } else {
            h->card_dat_oe = 1;
            h->card_dat = 0xE;
        }
        break;
    case DatState::ReadWait:
        h->card_dat_oe = 0;
        if (h->cycle >= h->wait_until) {
            h->dat_state = DatState::Send;
            h->card_dat_oe = 1;
            h->card_dat = h->read_nibbles[h->read_at++];
        }
        break;
    case DatState::Send:
        if (h->read_at < h->read_nibbles.size()) {
            h->card_dat = h->read_nibbles[h->read_at++];
        } else {
            h->card_dat_oe = 0;
            h->dat_state = DatState::Idle;
        }
        break;
    }
}

// -- the clock --------------------------------------------------------------------------------

static inline void tick(Harness* h) {
    Vmaglog_fast* t = h->top;
    t->clk = 1;
    t->eval();
    h->cycle++;
    // Outputs now hold what the next edge samples.
    sdram_edge(h);
    if (t->sd_clk && !h->sd_clk_before) {
        sd_edge(h);
        sd_lines(h);
    }
    h->sd_clk_before = t->sd_clk;
    while (!h->dq_due.empty() && h->dq_due.front().first <= h->cycle) {
        t->sdram_dq_i_in = h->dq_due.front().second;
        h->dq_due.pop_front();
    }
    for (int k = 0; k < h->channels; k++) {
        UartLine& line = h->lines[k];
        if (line.next_change <= h->cycle) {
            uart_step(line, h->cycle);
            uint32_t rx = t->uart_rx_in;
            rx = (rx & ~(1u << k)) | ((uint32_t)line.level << k);
            t->uart_rx_in = rx;
        }
    }
    while (!h->button.empty() && h->button.front().first <= h->cycle) {
        t->button_in = h->button.front().second;
        h->button.pop_front();
    }
    t->clk = 0;
    t->eval();
}

}  // namespace

#define EXPORT __attribute__((visibility("default")))

extern "C" {

EXPORT void* fast_new(int channels, int row_bits, int col_bits, int bank_bits, int data_bits) {
    Harness* h = new Harness;
    h->context = new VerilatedContext;
    h->top = new Vmaglog_fast{h->context};
    h->channels = channels;
    h->lines.resize(channels);
    h->row_bits = row_bits;
    h->col_bits = col_bits;
    h->bank_bits = bank_bits;
    h->data_bits = data_bits;
    h->memory.assign((size_t)1 << (row_bits + col_bits + bank_bits), 0);
    h->open_row.assign(1 << bank_bits, -1);
    Vmaglog_fast* t = h->top;
    t->clk = 0;
    t->uart_rx_in = (1u << channels) - 1;
    t->button_in = 0;
    t->sd_cmd_i_in = 1;
    t->sd_dat_i_in = 0xF;
    t->sdram_dq_i_in = 0;
    t->wb_go_in = 0;
    t->wb_adr_in = 0;
    t->wb_we_in = 0;
    t->wb_dat_w_in = 0;
    t->eval();
    return h;
}

EXPORT void fast_free(void* p) {
    Harness* h = (Harness*)p;
    h->top->final();
    delete h->top;
    delete h->context;
    delete h;
}

EXPORT void fast_callbacks(void* p, command_cb c, block_cb b, event_cb e) {
    Harness* h = (Harness*)p;
    h->on_command = c;
    h->on_block = b;
    h->on_programmed = e;
}

// Queue `n` bytes on a channel's line: start cycles nondecreasing and after what is queued.
EXPORT int fast_uart_push(void* p, int channel, int n, const int64_t* starts, const uint8_t* values,
                   const double* bit_cycles, const uint8_t* stops) {
    Harness* h = (Harness*)p;
    if (channel < 0 || channel >= h->channels) return -1;
    UartLine& line = h->lines[channel];
    bool was_empty = line.queue.empty();
    for (int i = 0; i < n; i++) line.queue.push_back({starts[i], bit_cycles[i], values[i], stops[i]});
    if (was_empty && line.bit == -1)
        line.next_change = std::max(line.queue.front().start, h->cycle + 1);
    return 0;
}

EXPORT int fast_uart_queued(void* p, int channel) {
    return (int)((Harness*)p)->lines[channel].queue.size();
}

EXPORT void fast_button(void* p, int64_t cycle, int level) {
    ((Harness*)p)->button.emplace_back(cycle, level);
}

// Run `cycles` clock cycles. Returns 0, or -1 when a callback asked to stop.
EXPORT int fast_run(void* p, int64_t cycles) {
    Harness* h = (Harness*)p;
    for (int64_t i = 0; i < cycles; i++) {
        tick(h);
        if (h->aborted) return -1;
    }
    return 0;
}

// One Wishbone access; returns the cycles it took, or -1 (a callback stopped the run),
// -2 (no acknowledgement within `limit` cycles). `*data` is the value written, or read.
EXPORT int fast_wishbone(void* p, int address, int write, uint32_t* data, int limit) {
    Harness* h = (Harness*)p;
    Vmaglog_fast* t = h->top;
    h->wb_accesses++;
    t->wb_adr_in = address;
    t->wb_we_in = write;
    t->wb_dat_w_in = *data;
    t->wb_go_in = 1;
    int64_t start = h->cycle;
    tick(h);
    t->wb_go_in = 0;
    if (h->aborted) return -1;
    for (int k = 0; k < limit; k++) {
        tick(h);
        if (h->aborted) return -1;
        if (t->wb_ack) {
            if (!write) *data = t->wb_dat_r;
            else {
                // A CSR field takes the value a cycle after the bridge's strobe.
                tick(h);
                if (h->aborted) return -1;
            }
            return (int)(h->cycle - start);
        }
    }
    return -2;
}

// Called from on_command: the card's response (nbits bits, first first; 0: none), sent
// after `gap` released clocks; `busy` cycles of DAT0 busy after it (R1b); a block to send
// after it (`data` 512 bytes or NULL) `read_delay` cycles after the response's end.
EXPORT void fast_sd_respond(void* p, int nbits, const uint8_t* bits, int gap, int64_t busy,
                     const uint8_t* data, int64_t read_delay) {
    Harness* h = (Harness*)p;
    h->response.assign(bits, bits + nbits);
    h->response_at = 0;
    h->busy_after_response = busy;
    h->read_pending = data != nullptr;
    if (data) {
        read_packet(h, data);
        h->read_delay = read_delay;
    }
    if (nbits > 0) {
        h->cmd_state = CmdState::Gap;
        h->gap = gap;
    } else if (busy > 0) {
        h->error("an R1b busy without a response");
    }
}

// Whether the card takes write blocks now (it is in rcv).
EXPORT void fast_sd_receive(void* p, int enabled) {
    ((Harness*)p)->rx_enabled = enabled != 0;
}

// Called from on_block: the CRC status token (3 bits, 0b010 accepted) after `gap` released
// clocks, then `busy` cycles of DAT0 busy, then on_programmed.
EXPORT void fast_sd_token(void* p, int token, int gap, int64_t busy) {
    Harness* h = (Harness*)p;
    h->token_bits = {0, (uint8_t)((token >> 2) & 1), (uint8_t)((token >> 1) & 1),
                     (uint8_t)(token & 1), 1};
    h->gap = gap;
    h->busy_cycles = busy;
    h->dat_state = DatState::TokenGap;
    if (gap <= 0) h->error("a CRC status token needs a gap of at least one clock");
}

EXPORT int64_t fast_cycle(void* p) { return ((Harness*)p)->cycle; }
EXPORT int fast_led(void* p) { return ((Harness*)p)->top->led; }

EXPORT void fast_stats(void* p, uint64_t* out) {
    Harness* h = (Harness*)p;
    out[0] = h->sdram_commands;
    out[1] = h->sd_edges;
    out[2] = h->sd_commands;
    out[3] = h->sd_blocks;
    out[4] = h->wb_accesses;
}

EXPORT int fast_error_count(void* p) { return (int)((Harness*)p)->errors.size(); }

EXPORT int fast_error(void* p, int index, char* buffer, int size) {
    Harness* h = (Harness*)p;
    if (index < 0 || index >= (int)h->errors.size() || size <= 0) return -1;
    std::strncpy(buffer, h->errors[index].c_str(), size - 1);
    buffer[size - 1] = 0;
    return 0;
}

}  // extern "C"
