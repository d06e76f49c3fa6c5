/*
 * rigctl_simavr.c - runs one rig firmware image under simavr with the host talking to it over a pty.
 *
 *   rigctl_simavr --board uno|mega [options] FIRMWARE.elf
 *
 * Common: UART0 is bridged to a pty (our own bridge, below); the line "PTY /dev/pts/N" on stdout names it. The core is paced to the wall clock (nanosleep on avr->cycle) unless
 * --no-pace; --clock-lock FILE also keeps it in lock step with the other board's harness and within the host's grant
 * (see "clock lock" below: one clock for the host and the boards).
 * The harness exits when its stdin closes, on "quit", or when its parent process dies (its parent pid changes; not
 * PR_SET_PDEATHSIG, which fires when the host *thread* that started it ends: the desktop app opens the rig in a
 * worker thread, and the boards vanished as it finished).
 * --reset-on-open emulates the Arduino's DTR auto-reset: each open() of the pty by a host (inotify IN_OPEN)
 * holds the core in reset for --boot-ms (the bootloader's wait) and restarts the firmware.
 *
 * Uno (ATmega328P): the ADC is fed with a mux-aware taxel signal. Three 74HC4051 share select lines PD4-PD6;
 * mux m drives A<m> with taxels 6m..6m+5. Rows of 18 ADC counts come from a waveform file (raw little-endian
 * uint16, n x 18, e.g. written by rigctl.simulation.hil from the physical model); a new row is taken at the
 * first conversion of every scan (select 0 on A0), so frame k carries row (k0 + k) mod n, and the counts are
 * converted to exactly the millivolts that simavr's ADC turns back into the same counts. stdin commands:
 * "wave PATH [BASE]" (load a waveform; row 0 = scan BASE if given, else the scan it starts at), "scan?" (reply "SCAN n=<scans so far> start=<scan of the waveform's row 0>"),
 * "sync" (a 1 ms pulse on the sync-in pin D2), "taxel_aa NF" (the anti-alias capacitor at every mux input, below). Timing: the sampler's probe pin
 * (PB0) and the transmitter's (PB1) are timed on avr->cycle; "ISR ..." lines report cycles per 1 ms tick.
 *
 * Mega (ATmega2560): emulates the HX711 (DOUT PE5, SCK PG5; --hx711-sps 10|80 with --hx711-clock-error, the
 * datasheet's 4-period settling as a sinc^4 filter, 24-bit two's complement, 25th clock = gain 128) with a spring
 * model (--spring-k: contact stiffness, g/mm) between the lead-screw actuator (STEP PE3, DIR PH3, --act-steps-per-mm) and the
 * load cell: force_g = k * max(0, x_mm - contact_mm) + bump; raw = offset + force_g * counts_per_g. Drives the
 * home switch (PH4, low at x <= 0). Watches the drum STEP (PB5)/DIR (PB4) pins and the index output (PH6):
 * "TEL ..." lines every --tel-ms of simulated time give step counts and the force; "IDX t=..." at each index
 * pulse; the drum index sensor on PL1 (ICP5) from the real drum angle ("ISENS t=..." at each mark; see
 * index_sensor_poll). stdin commands: "bump G" (an external force offset in g, e.g. to trip the force limit), "reset" (the
 * reset button: the firmware restarts, its EEPROM is kept).
 * Mega safety wiring (see "Mega: safety wiring" below): the stepper drivers' EN (PH5, active low, a pull-up on the
 * board: an input pin or a high output disables them) is observed, and a STEP pulse while the drivers are disabled
 * moves nothing ("TEL ... en=0|1 steps_disabled=N"); the e-stop input (PE4) is a normally-closed contact to GND
 * ("estop open" / "estop close"); "polarity -1|1" mounts the load cell the other way round (or back); "reset",
 * "brownout" and "poweron" reset the MCU with MCUSR's EXTRF, BORF or PORF set while the spring model keeps its state
 * (a reset under load); "hang" holds PA0 (D22) high until the next reset: the test image (mega_drum_test.elf, built
 * with RIGCTL_TEST_HOOKS) then hangs in loop(), for the watchdog test; "homeswitch broken|ok" breaks the home
 * switch's wire (it never closes) or mends it; "eeprom-flip OFFSET" flips bit 4 of one EEPROM byte (a corrupted
 * calibration record); "eeprom-corrupt OFFSET" flips it and browns the MCU out at once (a brown-out while writing
 * the EEPROM). A reset by the MCU itself (the watchdog) is reported as "RESET t=... cause=mcu".
 * Force-path faults (issue 55): "hx711 sck-broken" breaks the HX711's SCK wire (it is never clocked: DOUT stays low
 * after its next conversion and every bit the firmware reads is 0), "hx711 frozen" freezes its output at the value of
 * its last conversion (conversions go on at their rate, the same 24 bits each), "hx711 ok" mends both; "spring-k G"
 * gives the contact a stiffness of G g/mm (off the contact a plate swap; under load the force stays continuous, as
 * mega_force_g says), "spring-k default" puts the rig's own back. The HX711's input noise is modelled (Avia
 * HX711 datasheet: 50 nV rms at 10 SPS, 90 nV at 80 SPS at gain 128, one count = 40 mV / 2^24 = 2.38 nV: 21 and
 * 38 counts rms, Gaussian, a fixed seed).
 * Actuator direction: --actuator-reversed or "actuator reversed|ok" swaps the motor's coil pair (DIR high then moves it away from the
 * sensor) or mends it; each reversal of the steps that really move it is reported as "AREV t=<first step of the new
 * direction> dir=1|0 (1 = towards the sensor) last_t=<the last step of the old one>". "rxlog 1|0": an "RX t=..." line
 * each time host bytes arrive (when a request reached the board, to time the firmware's answer on the pins), and
 * "ASTEP t=... dir=..." at each actuator step that moves it. "link down|up" cuts the host's link (a pulled USB cable:
 * host bytes and the board's answers are lost) or restores it. "drum slip F" (0-1) makes the real drum turn F less
 * than its STEP pulses say (1 = stalled), "drum ok" ends it; "MARK t=..." at each speed mark (the disc's slots).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <pty.h>
#include <termios.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/inotify.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_eeprom.h"
#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_timer.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_core.h"
#include "sim_elf.h"
#include "sim_irq.h"

#include "../common/rigctl_wire.h"

#define N_TAXELS RIGCTL_N_TAXELS

static avr_t *avr;
static int is_uno;
static double sim_s(void);
static void extint_poll(void); /* simavr's level-trigger poll on only where the firmware asks for it (below) */

/* ================================ UART0 <-> pty bridge ================================
 * Our own bridge instead of simavr's uart_pty: uart_pty keeps 512-byte buffers in a separate thread and drops
 * bytes when that thread or the host falls behind for ~12 ms (a loaded 2-core CI machine does). Here the
 * firmware's bytes go into a 4 MiB ring drained by non-blocking writes from the simulation thread, and host
 * bytes are fed to the UART only while its receive FIFO has room (simavr's XON/XOFF irqs). */
#define TX_RING_SIZE (1u << 22)
static uint8_t *tx_ring;
static size_t tx_head, tx_tail; /* bytes [tx_tail, tx_head) wait for the host */
static uint64_t tx_lost;
static int pty_master = -1, pty_slave = -1;
static uint64_t rx_total; /* bytes the bridge has read from the pty (the host's, and junk while the link is cut) */
static void rx_count(ssize_t r); /* counts them and publishes the count (clock lock) */
static void tx_stamp(void); /* the bridge's last write to the pty, published (clock lock) */
static char pty_name[128];
static int uart_xon = 1;
static atomic_int link_down_req; /* 1 = the host's link is cut (USB pulled): host bytes and board bytes are lost */
static atomic_int rxlog_req; /* 1 = "RX t=..." each time host bytes arrive, "ASTEP t=... dir=..." at each actuator step */
/* The Uno's stream leaves in USB-sized bursts, as through the board's 16U2 (which sends its 128-byte ring through one
 * 64-byte endpoint, when 96 bytes are in or every ~4 ms): bytes wait until TX_BATCH_BYTES are pending or the oldest
 * has waited TX_BATCH_CYCLES (1 ms of simulated time), at most, then go in one write, instead of a write at every
 * 0.1 ms poll (~5,000 writes a second, each a pty wake-up in the kernel). The host sees the same bytes no later than
 * 1 ms after the UART sent them (the bench: up to ~4 ms). The Mega's Modbus replies are sent at the next poll. */
#define TX_BATCH_BYTES 64
#define TX_BATCH_CYCLES 16000u
static uint64_t tx_oldest_cycle; /* avr->cycle when the oldest waiting byte was sent by the UART */
static uint8_t rx_buf[4096];
static size_t rx_len, rx_pos;
static avr_irq_t *uart_in_irq;

static void uart_out_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    size_t next = (tx_head + 1) & (TX_RING_SIZE - 1);
    if (next == tx_tail) {
        tx_lost++;
        return;
    }
    if (tx_head == tx_tail) tx_oldest_cycle = avr->cycle;
    tx_ring[tx_head] = (uint8_t)value;
    tx_head = next;
}

static void uart_xon_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value) uart_xon = 1;
}

static void uart_xoff_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value) uart_xon = 0;
}

static int bridge_open(void)
{
    struct termios tio;
    if (openpty(&pty_master, &pty_slave, pty_name, NULL, NULL) < 0) return -1;
    tcgetattr(pty_slave, &tio);
    cfmakeraw(&tio);
    tcsetattr(pty_slave, TCSANOW, &tio);
    fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
    fcntl(pty_master, F_SETFD, FD_CLOEXEC);
    fcntl(pty_slave, F_SETFD, FD_CLOEXEC);
    tx_ring = malloc(TX_RING_SIZE);
    /* the firmware's UART output is binary: no stdio dump, and no usleep when it polls UCSR0A */
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POOL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_out_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), uart_xon_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), uart_xoff_hook, NULL);
    uart_in_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    return tx_ring ? 0 : -1;
}

/* move bytes both ways; called from the simulation loop every 0.1 ms of simulated time; readable: poll() saw host
 * bytes (or a hang-up) on the pty */
static void bridge_poll(int readable)
{
    if (atomic_load(&link_down_req)) { /* USB pulled: nothing reaches the board, nothing it sends reaches the host */
        uint8_t junk[512];
        ssize_t r;
        while ((r = read(pty_master, junk, sizeof junk)) > 0) rx_count(r);
        tx_tail = tx_head;
        rx_pos = rx_len = 0;
        return;
    }
    size_t pending = (tx_head - tx_tail) & (TX_RING_SIZE - 1);
    if (is_uno && pending < TX_BATCH_BYTES && avr->cycle - tx_oldest_cycle < TX_BATCH_CYCLES) pending = 0;
    while (pending && tx_tail != tx_head) {
        size_t n = tx_head > tx_tail ? tx_head - tx_tail : TX_RING_SIZE - tx_tail;
        ssize_t w = write(pty_master, tx_ring + tx_tail, n);
        if (w <= 0) break; /* EAGAIN: the host is behind; keep the bytes */
        tx_tail = (tx_tail + (size_t)w) & (TX_RING_SIZE - 1);
        tx_stamp();
    }
    if (rx_pos == rx_len && readable) {
        ssize_t r = read(pty_master, rx_buf, sizeof rx_buf);
        rx_pos = 0;
        rx_len = r > 0 ? (size_t)r : 0;
        if (r > 0) rx_count(r);
        if (r > 0 && atomic_load(&rxlog_req)) printf("RX t=%.6f n=%zd\n", sim_s(), r); /* a request's arrival */
    }
    while (uart_xon && rx_pos < rx_len) avr_raise_irq(uart_in_irq, rx_buf[rx_pos++]);
}

/* a (DTR) reset: whatever the old firmware had not yet sent and host bytes in flight are dropped */
static void bridge_reset(void)
{
    tx_tail = tx_head;
    rx_pos = rx_len = 0;
    uart_xon = 1;
}

/* ================================ bootloader and DTR auto-reset ================================
 * --bootloader HEX loads a bootloader image (Debian's arduino-core-avr: stk500v2 for the Mega, optiboot for the Uno)
 * into flash beside the sketch, the way a flashed board holds them: the image goes to its own addresses (the boot
 * section at the top of flash), and the reset vector moves to its start, which is what the BOOTRST fuse does on the
 * chip (simavr has no fuse model: avr->reset_pc is that fuse). Every reset then enters the bootloader, which starts
 * the sketch at 0 when its window passes. With --reset-on-open, a host opening the pty resets the MCU at once (as
 * the Uno/Mega's 16U2 does: opening the port asserts DTR, whose edge reaches RESET through a 100 nF capacitor; a
 * pty has no DTR, so the open itself is detected: inotify IN_OPEN on the slave), MCUSR = EXTRF, and the bootloader
 * runs in simulated real time; host bytes written after the open reach it. Without --bootloader the old model
 * stays: the core is held for --boot-ms, then the sketch starts. */
static double sim_s(void);
#define MCUSR_ADDR 0x54 /* MCUSR data-space address, ATmega328P and ATmega2560 */
#define MCUSR_EXTRF 1
static int boot_loaded;
static uint32_t boot_start;
static int boot_in_loader;  /* the MCU runs the bootloader (since the last reset) */
static double boot_reset_t; /* simulated time of that reset */

/* Intel HEX into flash (records 00 data, 01 end, 02/04 segment/linear base; 03/05 start addresses ignored: simavr's
 * read_ihex_chunks refuses optiboot's type-03 record). Returns the lowest address loaded, or -1. */
static long boot_read_hex(const char *path)
{
    FILE *f = fopen(path, "r");
    if (!f) return -1;
    char line[600];
    uint32_t base = 0;
    long lowest = -1;
    int ok = 0;
    while (fgets(line, sizeof line, f)) {
        unsigned n, addr, type, sum = 0, b;
        if (line[0] != ':' || sscanf(line + 1, "%2x%4x%2x", &n, &addr, &type) != 3 || strlen(line) < 11 + 2 * n) break;
        uint8_t data[256];
        for (unsigned i = 0; i < n + 5; i++) {
            if (sscanf(line + 1 + 2 * i, "%2x", &b) != 1) goto done;
            sum += b;
            if (i >= 4 && i < 4 + n) data[i - 4] = (uint8_t)b;
        }
        if (sum & 0xFF) break; /* checksum */
        if (type == 0) {
            uint32_t a = base + addr;
            if (a + n > avr->flashend + 1) break;
            memcpy(avr->flash + a, data, n);
            if (lowest < 0 || a < (uint32_t)lowest) lowest = a;
            if (a + n > avr->codeend) avr->codeend = a + n;
        } else if (type == 1) {
            ok = 1;
            break;
        } else if (type == 2 && n == 2) {
            base = (uint32_t)((data[0] << 8) | data[1]) << 4;
        } else if (type == 4 && n == 2) {
            base = (uint32_t)((data[0] << 8) | data[1]) << 16;
        }
    }
done:
    fclose(f);
    return ok ? lowest : -1;
}

static int boot_load(const char *hex)
{
    long lowest = boot_read_hex(hex);
    if (lowest < 0) return -1;
    boot_start = (uint32_t)lowest;
    avr->reset_pc = boot_start; /* BOOTRST programmed: reset enters the boot section */
    avr->pc = boot_start;
    boot_loaded = 1;
    boot_in_loader = 1; /* power-on: the MCU starts in the bootloader */
    return 0;
}

/* "APP t=... boot_s=..." when the sketch starts after a reset: how long the bootloader held the MCU (checked every
 * 0.1 ms of simulated time; the sketch never runs code in the boot section) */
static void boot_watch(void)
{
    if (boot_in_loader && avr->pc < boot_start) {
        boot_in_loader = 0;
        printf("APP t=%.6f boot_s=%.4f\n", sim_s(), sim_s() - boot_reset_t);
    } else if (!boot_in_loader && boot_loaded && avr->pc >= boot_start) { /* any other reset (watchdog, button) */
        boot_in_loader = 1;
        boot_reset_t = sim_s();
    }
}

/* the host opened the port: DTR reset into the bootloader (external reset flag set) */
static void boot_dtr_reset(void (*after_reset)(void))
{
    avr_reset(avr);
    extint_poll();
    avr->data[MCUSR_ADDR] |= (1 << MCUSR_EXTRF);
    tx_tail = tx_head; /* what the old firmware had not yet sent is gone; host bytes sent after the open stay */
    uart_xon = 1;
    if (after_reset) after_reset();
    boot_in_loader = 1;
    boot_reset_t = sim_s();
    printf("RESET t=%.6f cause=dtr\n", sim_s());
}

/* ---- options ---- */
static int opt_pace = 1;
static int opt_reset_on_open = 0;
static const char *opt_bootloader = NULL;
static double opt_boot_ms = 200.0;
static _Atomic double opt_spring_k = 250.0; /* contact stiffness, g per mm (MechanicsConfig's default); "spring-k G" */
static double opt_spring_k0 = 250.0;        /* the rig's own (--spring-k): "spring-k default" */
static double opt_contact_mm = 5.0;
static double opt_contact_mm0 = 5.0;          /* the rig's plates' surface (--contact-mm): a swap off the contact's */
static _Atomic double spring_k_req = 0.0;     /* "spring-k G" asked, not yet applied (0: none) */
static double opt_act_steps_per_mm = 400.0;
static double opt_rear_stop_mm = 1.0;      /* the actuator's mechanical rear stop, mm behind the home switch */
/* the actuator driver's stall current (--actuator-stall-g G, 0 = none, the default): a step towards the sensor that
 * would make the spring's force exceed G is lost, as a driver whose Vref is set for a stall near 1.5 x the largest
 * force skips (docs/hardware/wiring.md "Driver current": A4988 I = Vref / (8 R_sense), Allegro datasheet "Current
 * Regulation"; torque about proportional to current, F = 2 pi eta T / lead). Off in every safety test */
static double opt_stall_g = 0.0;
static double opt_counts_per_g = 420.0;    /* LOADCELL_SCALE_X100 default / 100 */
static long opt_loadcell_offset = 8000;
static double opt_tel_ms = 50.0;
static double opt_max_seconds = 0.0;
static const char *opt_clock_lock = NULL;

/* ---- stdin commands (reader thread -> main loop) ---- */
static atomic_int quit_requested;
static atomic_int reset_requested;
static atomic_int sync_requests;
static atomic_int bump_g_x1000;
static atomic_int reset_cause_req;   /* MCUSR bits for the next "reset": EXTRF 2, BORF 4, PORF 1 */
static atomic_int estop_open_req;    /* 1 = the e-stop contact is open */
static atomic_int hang_req;          /* 1 = PA0 high until the next reset */
static atomic_int polarity_req = 1;  /* +1 or -1: the load cell's sign */
static atomic_int home_broken_req;   /* 1 = the home switch never closes */
static atomic_int home_stuck_req;    /* 1 = the home switch reads closed wherever the actuator is (D7 shorted) */
static _Atomic double cell_gain_req = 1.0;   /* the load cell's sensitivity against its calibration ("cell gain X") */
static _Atomic double cell_offset_g_req;     /* the cell's zero moved by this many g ("cell offset G") */
static _Atomic double act_slip_req;          /* "coupling slip F": F of the actuator's steps wind the coupling up */
static _Atomic double act_lost_req;          /* "steps lost F": F of the actuator's steps are lost for good */
static _Atomic double hx_dout_noise_req;     /* "hx711 dout-noise P": each DOUT bit read flips with probability P */
static atomic_int en_stuck_req;      /* 1 = the drivers' EN input stuck active: they drive whatever the MCU says */
static atomic_int hx_rate_req;       /* "hx711 rate N": the RATE pin changed, the board powered on again (0: none) */
static atomic_int drum_reversed_req; /* 1 = the drum motor's coil pair swapped: the real drum turns backwards */
static const char *opt_eeprom_write;
static char eeprom_write_req[160];   /* "eeprom-write OFF:HEX" then a power-on: applied by the simulation thread */
static atomic_int eeprom_write_pending;
static atomic_int eeprom_flip_req = -1; /* EEPROM offset to corrupt, -1 = none */
static atomic_int eeprom_corrupt_req = -1; /* the same, then a brown-out reset in the same step */
static atomic_int hx_sck_broken_req;  /* 1 = the HX711's SCK wire is broken */
static atomic_int hx_frozen_req;      /* 1 = the HX711's output frozen */
static atomic_int act_reversed_req;  /* 1 = the actuator motor's coil pair swapped: DIR high moves it away */
static _Atomic double opt_aa_c_nf; /* Uno: the anti-alias C_aa at each mux input, nF (--aa-c-nf, "taxel_aa NF") */
static _Atomic double drum_slip_req; /* "drum slip F": the real drum turns F less than its steps say (1: stalled) */
static pthread_mutex_t wave_lock = PTHREAD_MUTEX_INITIALIZER;
static uint16_t *wave;     /* n_rows x 18 ADC counts */
static size_t wave_rows;
static uint16_t *wave_pending; /* loaded by the stdin thread, swapped in at the start of the next scan */
static size_t wave_pending_rows;
static long long wave_pending_base = -1; /* scan number of the pending waveform's row 0 (-1: the scan it starts at) */
static uint64_t scan_count;       /* Uno: ADC scans so far (one per 1 ms tick; a tick without one counts too) */
static uint64_t scan_base;        /* scan_count when the playing waveform started (row 0) */
static int scans_running;         /* the Uno has started a conversion (or ticked with its ADC off) since its last reset
                                   * (written by the simulation thread under wave_lock; a waveform loaded before then
                                   * plays from the first scan) */

static int mux_set_taxel_ohm(const char *args);

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static double sim_s(void)
{
    return (double)avr->cycle / (double)avr->frequency;
}

static int load_wave(const char *path, long long base, int *at_once)
{
    FILE *f = fopen(path, "rb");
    if (!f) return -1;
    fseek(f, 0, SEEK_END);
    long size = ftell(f);
    fseek(f, 0, SEEK_SET);
    if (size <= 0 || size % (2 * N_TAXELS)) {
        fclose(f);
        return -1;
    }
    uint16_t *buf = malloc(size);
    size_t got = fread(buf, 1, size, f);
    fclose(f);
    if ((long)got != size) {
        free(buf);
        return -1;
    }
    for (long i = 0; i < size / 2; i++) { /* file is little-endian */
        uint8_t *b = (uint8_t *)&buf[i];
        buf[i] = (uint16_t)(b[0] | (b[1] << 8));
        if (buf[i] > RIGCTL_ADC_MAX) buf[i] = RIGCTL_ADC_MAX;
    }
    pthread_mutex_lock(&wave_lock);
    uint16_t *old = wave_pending;
    uint16_t *old_playing = NULL;
    if (!scans_running) {
        /* no scan since the reset (the bootloader, or the firmware's setup): no row boundary is coming to swap
         * it in, and the first scan must already play it, from row 0 */
        old_playing = wave;
        wave = buf;
        wave_rows = size / (2 * N_TAXELS);
        scan_base = 0;
        wave_pending = NULL;
        *at_once = 1;
    } else {
        wave_pending = buf;
        wave_pending_rows = size / (2 * N_TAXELS);
        wave_pending_base = base;
    }
    pthread_mutex_unlock(&wave_lock);
    free(old);
    free(old_playing);
    return 0;
}

static void *stdin_thread(void *arg)
{
    (void)arg;
    char line[1024];
    while (fgets(line, sizeof line, stdin)) {
        line[strcspn(line, "\r\n")] = 0;
        if (!strncmp(line, "wave ", 5)) {
            /* "wave PATH [BASE]": BASE = the scan number row 0 stands for (rows already due are skipped at the
             * swap, so the waveform stays in phase however late it arrives) */
            long long base = -1;
            char *sp = strchr(line + 5, ' ');
            if (sp) {
                *sp = 0;
                base = atoll(sp + 1);
            }
            int at_once = 0;
            if (load_wave(line + 5, base, &at_once)) printf("ERR wave %s\n", line + 5);
            else printf("OK wave %s\n", at_once ? "playing" : "pending"); /* pending: from the next row boundary */
        } else if (!strcmp(line, "scan?")) { /* which row of the waveform plays now */
            printf("SCAN n=%llu start=%llu\n", (unsigned long long)scan_count, (unsigned long long)scan_base);
        } else if (!strncmp(line, "taxel_ohm ", 10)) {
            if (mux_set_taxel_ohm(line + 10)) printf("ERR taxel_ohm\n");
            else printf("OK taxel_ohm\n");
        } else if (!strncmp(line, "taxel_aa ", 9)) {
            double nf = atof(line + 9);
            if (nf < 0.0 || nf > 10000.0) {
                printf("ERR taxel_aa\n");
            } else {
                atomic_store(&opt_aa_c_nf, nf);
                printf("OK taxel_aa\n");
            }
        } else if (!strcmp(line, "sync")) {
            atomic_fetch_add(&sync_requests, 1);
        } else if (!strncmp(line, "bump ", 5)) {
            atomic_store(&bump_g_x1000, (int)(atof(line + 5) * 1000.0));
            printf("OK bump\n");
        } else if (!strcmp(line, "reset") || !strcmp(line, "brownout") || !strcmp(line, "poweron")) {
            /* reset button / brown-out / power cycle: the sketch starts afresh; the SRAM survives but a power cycle;
             * EEPROM and the mechanics kept */
            atomic_store(&reset_cause_req, line[0] == 'r' ? 2 : line[0] == 'b' ? 4 : 1);
            atomic_store(&reset_requested, 1);
        } else if (!strcmp(line, "estop open") || !strcmp(line, "estop close")) {
            atomic_store(&estop_open_req, line[6] == 'o');
            printf("OK estop\n");
        } else if (!strcmp(line, "hang")) {
            atomic_store(&hang_req, 1);
            printf("OK hang\n");
        } else if (!strcmp(line, "homeswitch broken") || !strcmp(line, "homeswitch ok") ||
                   !strcmp(line, "homeswitch stuck")) {
            atomic_store(&home_broken_req, line[11] == 'b');
            atomic_store(&home_stuck_req, line[11] == 's');
            printf("OK homeswitch\n");
        } else if (!strncmp(line, "cell gain ", 10) || !strncmp(line, "cell offset ", 12)) {
            if (line[5] == 'g') atomic_store(&cell_gain_req, atof(line + 10));
            else atomic_store(&cell_offset_g_req, atof(line + 12));
            printf("OK cell\n");
        } else if (!strncmp(line, "coupling slip ", 14) || !strncmp(line, "steps lost ", 11)) {
            double f = atof(line[0] == 'c' ? line + 14 : line + 11);
            atomic_store(line[0] == 'c' ? &act_slip_req : &act_lost_req, f < 0.0 ? 0.0 : f > 1.0 ? 1.0 : f);
            printf("OK %s\n", line[0] == 'c' ? "coupling" : "steps");
        } else if (!strncmp(line, "hx711 dout-noise ", 17)) {
            double p = atof(line + 17);
            atomic_store(&hx_dout_noise_req, p < 0.0 ? 0.0 : p > 1.0 ? 1.0 : p);
            printf("OK hx711\n");
        } else if (!strncmp(line, "hx711 rate ", 11)) {
            int r = atoi(line + 11);
            if (r == 10 || r == 80) {
                atomic_store(&hx_rate_req, r);
                printf("OK hx711\n");
            } else {
                printf("ERR hx711\n");
            }
        } else if (!strcmp(line, "driver en-stuck") || !strcmp(line, "driver ok")) {
            atomic_store(&en_stuck_req, line[7] == 'e');
            printf("OK driver\n");
        } else if (!strncmp(line, "eeprom-write ", 13) && strlen(line + 13) < sizeof eeprom_write_req) {
            if (!atomic_load(&eeprom_write_pending)) {
                strcpy(eeprom_write_req, line + 13);
                atomic_store(&eeprom_write_pending, 1);
            }
        } else if (!strncmp(line, "eeprom-flip ", 12)) {
            atomic_store(&eeprom_flip_req, atoi(line + 12));
        } else if (!strncmp(line, "eeprom-corrupt ", 15)) {
            atomic_store(&eeprom_corrupt_req, atoi(line + 15));
        } else if (!strcmp(line, "hx711 sck-broken") || !strcmp(line, "hx711 frozen") || !strcmp(line, "hx711 ok")) {
            atomic_store(&hx_sck_broken_req, line[6] == 's');
            atomic_store(&hx_frozen_req, line[6] == 'f');
            printf("OK hx711\n");
        } else if (!strncmp(line, "spring-k ", 9)) {
            double k = strcmp(line + 9, "default") ? atof(line + 9) : opt_spring_k0;
            if (k > 0.0 && k <= 1e6) {
                atomic_store(&spring_k_req, k); /* applied by the core's thread (mega_force_g): force continuous */
                printf("OK spring-k\n");
            } else {
                printf("ERR spring-k\n");
            }
        } else if (!strcmp(line, "actuator reversed") || !strcmp(line, "actuator ok")) {
            atomic_store(&act_reversed_req, line[9] == 'r');
            printf("OK actuator\n");
        } else if (!strcmp(line, "drum reversed") || !strcmp(line, "drum forward")) {
            atomic_store(&drum_reversed_req, line[5] == 'r');
            printf("OK drum\n");
        } else if (!strncmp(line, "drum slip ", 10) || !strcmp(line, "drum ok")) {
            double f = line[5] == 's' ? atof(line + 10) : 0.0;
            atomic_store(&drum_slip_req, f < 0.0 ? 0.0 : f > 1.0 ? 1.0 : f);
            printf("OK drum\n");
        } else if (!strcmp(line, "link down") || !strcmp(line, "link up")) {
            atomic_store(&link_down_req, line[5] == 'd');
            printf("OK link\n");
        } else if (!strncmp(line, "rxlog ", 6)) {
            atomic_store(&rxlog_req, atoi(line + 6) != 0);
            printf("OK rxlog\n");
        } else if (!strncmp(line, "polarity ", 9)) {
            atomic_store(&polarity_req, atoi(line + 9) < 0 ? -1 : 1);
            printf("OK polarity\n");
        } else if (!strcmp(line, "quit")) {
            break;
        }
    }
    atomic_store(&quit_requested, 1); /* stdin closed: the host is gone */
    return NULL;
}

/* the host process gone (re-parented: its pid no longer our parent's) while something else keeps our stdin open, e.g.
 * a forked child of the host: quit as if stdin had closed */
static pid_t host_pid;
static void *parent_watch_thread(void *arg)
{
    (void)arg;
    while (!atomic_load(&quit_requested)) {
        if (getppid() != host_pid) {
            atomic_store(&quit_requested, 1);
            break;
        }
        usleep(200000);
    }
    return NULL;
}

/* ================================ Uno: mux-aware taxel ADC ================================ */
static uint8_t mux_sel;          /* select lines PD4..PD6 as the pins show them */
static size_t scan_row;
static void mux_before_select(void);
static avr_irq_t *adc_irq_base;
static uint64_t probe_rise[3], probe_total[3], probe_window_sum[3], probe_window_max[3], probe_window[3];
/* CPU load of the Uno: cycles spent with interrupts off (inside an ISR, its entry and exit included) or with a probe
 * pin high (an ISR's body, the tick's frame building with interrupts enabled, loop()'s encoder on PB2), per 1 ms
 * tick window (16 000 cycles): mean and largest since the last report, largest since start */
static int probes_high; /* bit p: probe p is high */
static unsigned sp_min = 0xFFFF; /* lowest stack pointer seen since start (the stack's high-water mark) */
static uint64_t busy_window, busy_window_sum, busy_report_sum, busy_report_ticks, busy_report_max, busy_max;

static uint64_t busy_window_start, busy_window_end = 16000u; /* the window's cycles [start, end) */

/* called for every step of the core: the window is found with a division only when the step left it */
static void busy_account(uint64_t cycle_before, int busy)
{
    if (cycle_before < busy_window_start || cycle_before >= busy_window_end) {
        uint64_t w = cycle_before / 16000u;
        busy_window_start = w * 16000u;
        busy_window_end = busy_window_start + 16000u;
        busy_report_sum += busy_window_sum;
        busy_report_ticks += w - busy_window;
        if (busy_window_sum > busy_report_max) busy_report_max = busy_window_sum;
        if (busy_window_sum > busy_max) busy_max = busy_window_sum;
        busy_window_sum = 0;
        busy_window = w;
    }
    if (busy) busy_window_sum += avr->cycle - cycle_before;
    unsigned sp = avr->data[0x5D] | ((unsigned)avr->data[0x5E] << 8); /* SPL, SPH */
    if (sp < sp_min && sp >= 0x100) sp_min = sp;
}
static uint64_t sync_off_cycle;
static avr_irq_t *sync_pin;

static void sel_pin_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    int bit = (int)(intptr_t)param;
    mux_before_select();
    if (value & 1) mux_sel |= (uint8_t)(1 << bit);
    else mux_sel &= (uint8_t)~(1 << bit);
}

static uint16_t taxel_value(size_t row, int taxel)
{
    uint16_t v;
    pthread_mutex_lock(&wave_lock);
    if (wave && wave_rows) v = wave[(row % wave_rows) * N_TAXELS + taxel];
    else v = (uint16_t)((row * 7 + taxel * 53) % (RIGCTL_ADC_MAX + 1)); /* default pattern */
    pthread_mutex_unlock(&wave_lock);
    return v;
}

/* ================================ Uno: multiplexer settling (RC model) ================================
 * Per taxel, the anti-alias RC at its 74HC4051 input Yn (docs/firmware.md, "Taxel source impedance and anti-alias
 * filter"): the taxel's source impedance (--taxel-ohm, per taxel with stdin "taxel_ohm I OHM"; R_s + R_aa) charges
 * a capacitor C_aa to ground at Yn (--aa-c-nf or stdin "taxel_aa NF": the documented 15 nF; default 0 = none fitted,
 * so a waveform's codes come back exact). Each multiplexer's common node
 * is a capacitor (--mux-c-pf, 25 pF: NXP/TI 74HC4051 datasheets, C_S common) joined to the selected input's C_aa
 * through the switch's on-resistance (--mux-ron-ohm, 180 Ohm: ~70-180 Ohm at 4.5 V); R_on x C is a few ns, so a
 * switch shares the node's charge with C_aa at once and the two then charge together through the source impedance:
 * tau = (R_s + R_on) x (C_aa + 25 pF [+ 14 pF]). An unselected C_aa charges alone (tau = R_s x C_aa). Y6 and Y7 are
 * tied to GND (docs/hardware): selecting them discharges the node. The ATmega328P's sample-and-hold capacitor
 * (--sh-c-pf, 14 pF: ATmega328P datasheet, "Analog Input Circuitry") is connected to the input ADMUX selects (from
 * the ADMUX write, or from the end of a running conversion: the datasheet's ADMUX update rule; channel 15 = GND
 * discharges it) and shares its charge with that node when it moves. One PORTD store changes the three select lines
 * in the same cycle (simavr raises one pin at a time): the new selection is applied once the cycle has moved on.
 * The conversion samples 1.5 ADC clocks after ADSC (13.5 for the first after ADEN), and that voltage is what
 * simavr's ADC converts. Source voltages are the waveform's counts at the centre of their code ((c + 0.5) LSB), so an
 * injected value comes back exact exactly when the error stays below 0.5 LSB; voltages go to simavr in units of
 * 0.1 mV (AVCC given as 50000). The taxels' source values change once per scan, when its last conversion has been
 * started (the row swap below), and, while the board does not scan (its ADC off: the stream stopped), once per tick,
 * at the tick interrupt (uno_tick_row): a row is a ms of the board's time either way. "MUX ..." lines report the largest error (sampled voltage minus the taxel's filtered
 * signal: its source through its RC alone, with nothing switching at it; in LSB) per second of simulated time, and the longest scan (the first conversion's
 * ADSC, i.e. the tick, to the end of the last conversion, us: it must end inside the 1 ms tick). */
#define MUX_N 3
#define ADC_UNITS_PER_MV 10.0 /* ADC injection units (0.1 mV) */
#define M328_ADCSRA 0x7A      /* ATmega328P data-space addresses */
#define M328_ADMUX 0x7C
#define ADC_CH_GND 15         /* ADMUX MUX3:0 = 1111: 0 V (GND) */
static double opt_taxel_ohm = 47000.0;
static double opt_mux_ron_ohm = 180.0;
static double opt_mux_c_pf = 25.0;
static double opt_sh_c_pf = 14.0;
static _Atomic double taxel_ohm[N_TAXELS]; /* set by the stdin thread too */
static double node_mv[MUX_N];        /* voltage of each mux common node (and of the C_aa it is connected to) */
static uint64_t node_cycle[MUX_N];   /* when node_mv was last brought up to date */
static int node_taxel[MUX_N];        /* the taxel each node is connected to now, -1 = Y6/Y7 (GND) */
static double aa_mv[N_TAXELS];       /* voltage of each taxel's C_aa while not connected to its node */
static uint64_t aa_cycle[N_TAXELS];
static double ideal_mv[N_TAXELS];    /* what each C_aa would hold with nothing switching at it: the filtered signal */
static uint64_t ideal_cycle[N_TAXELS];
static uint64_t sel_pending_cycle;   /* the select lines changed in this cycle: applied once it is over */
static int sel_pending;
static int sh_ch = 0;                /* ADC input the sample-and-hold capacitor is connected to (ADMUX, 0 at reset) */
static double sh_mv;                 /* its voltage */
static int sh_pending = -1;          /* ADMUX written during a conversion: the input it connects at conv_end */
static uint64_t adc_conv_end;        /* cycle the running conversion ends */
static int adc_first_conv = 1;       /* the first conversion after reset takes 25 ADC clocks, samples at 13.5 */
static double mux_err_max_lsb, mux_err_window_lsb;
static uint64_t mux_conversions;
static uint64_t scan_first_cycle;           /* ADSC of the scan's first conversion (the tick interrupt's start) */
static double scan_us_window, scan_us_max;  /* longest scan: first ADSC to the end of the last conversion, us */

static double lsb_mv(void)
{
    return 5000.0 / 1023.0;
}

static double taxel_source_mv(size_t row, int taxel)
{
    return (taxel_value(row, taxel) + 0.5) * lsb_mv();
}

/* the taxel mux m connects with the select lines as they are (-1: Y6/Y7, tied to GND) */
static int mux_taxel(int m)
{
    return mux_sel < 6 ? m * 6 + mux_sel : -1;
}

static double aa_c_pf(void)
{
    return opt_aa_c_nf * 1000.0;
}

/* capacitance charging with node m (its C_aa, its own 25 pF, the sample-and-hold if ADMUX selects it), pF */
static double node_c_pf(int m)
{
    return (node_taxel[m] >= 0 ? aa_c_pf() : 0.0) + opt_mux_c_pf + (sh_ch == m ? opt_sh_c_pf : 0.0);
}

/* voltage of node m after dt_s more seconds with the present connection (no state change) */
static double mux_node_after(int m, double dt_s)
{
    int taxel = node_taxel[m];
    double target = taxel >= 0 ? taxel_source_mv(scan_row, taxel) : 0.0;
    double r = taxel >= 0 ? taxel_ohm[taxel] + opt_mux_ron_ohm : opt_mux_ron_ohm;
    double tau = r * node_c_pf(m) * 1e-12;
    if (dt_s <= 0.0) return node_mv[m];
    if (tau <= 0.0) return target;
    return target + (node_mv[m] - target) * exp(-dt_s / tau);
}

/* an unconnected C_aa brought up to `cycle` (it charges alone through the source impedance) */
static void aa_to(int t, uint64_t cycle)
{
    for (int m = 0; m < MUX_N; m++)
        if (node_taxel[m] == t) return; /* connected: it is the node's voltage (aa_mv is set when it leaves) */
    if (cycle <= aa_cycle[t]) return;
    double tau = taxel_ohm[t] * aa_c_pf() * 1e-12, target = taxel_source_mv(scan_row, t);
    double dt = (double)(cycle - aa_cycle[t]) / avr->frequency;
    aa_mv[t] = tau > 0.0 ? target + (aa_mv[t] - target) * exp(-dt / tau) : target;
    aa_cycle[t] = cycle;
}

/* the taxel's filtered signal at `cycle` (its RC alone, unloaded): what an ideal sampler would read */
static double ideal_to(int t, uint64_t cycle)
{
    if (cycle > ideal_cycle[t]) {
        double tau = taxel_ohm[t] * aa_c_pf() * 1e-12, target = taxel_source_mv(scan_row, t);
        double dt = (double)(cycle - ideal_cycle[t]) / avr->frequency;
        ideal_mv[t] = tau > 0.0 ? target + (ideal_mv[t] - target) * exp(-dt / tau) : target;
        ideal_cycle[t] = cycle;
    }
    return ideal_mv[t];
}

static void mux_nodes_to(uint64_t cycle)
{
    for (int m = 0; m < MUX_N; m++) {
        if (cycle > node_cycle[m]) {
            node_mv[m] = mux_node_after(m, (double)(cycle - node_cycle[m]) / avr->frequency);
            node_cycle[m] = cycle;
        }
        if (sh_ch == m) sh_mv = node_mv[m];
    }
}

/* the select lines' new value takes effect (at sel_pending_cycle): each node leaves its input's C_aa and joins the
 * new one's (charge sharing), or is discharged by Y6/Y7 */
static void mux_connect(void)
{
    for (int m = 0; m < MUX_N; m++) {
        int old = node_taxel[m], t = mux_taxel(m);
        if (t == old) continue;
        double c_node = opt_mux_c_pf + (sh_ch == m ? opt_sh_c_pf : 0.0);
        if (old >= 0) { /* C_aa keeps the common voltage and charges on alone */
            aa_mv[old] = node_mv[m];
            aa_cycle[old] = node_cycle[m];
        }
        if (t >= 0) {
            aa_to(t, node_cycle[m]);
            node_mv[m] = (c_node * node_mv[m] + aa_c_pf() * aa_mv[t]) / (c_node + aa_c_pf());
        } else {
            node_mv[m] = 0.0; /* Y6/Y7 at GND through R_on: a few ns */
        }
        node_taxel[m] = t;
        if (sh_ch == m) sh_mv = node_mv[m];
    }
}

/* the sample-and-hold capacitor moves to input ch (ADC_CH_GND: discharged): charge sharing with that node */
static void mux_sh_connect(int ch)
{
    if (ch == sh_ch) return;
    if (ch >= 0 && ch < MUX_N) {
        double c = node_c_pf(ch); /* without the S/H yet: sh_ch != ch */
        node_mv[ch] = (c * node_mv[ch] + opt_sh_c_pf * sh_mv) / (c + opt_sh_c_pf);
        sh_mv = node_mv[ch];
    } else if (ch == ADC_CH_GND) {
        sh_mv = 0.0;
    }
    sh_ch = ch;
}

/* bring every node up to `cycle`, applying a select change and an ADMUX change that took effect on the way */
static void mux_advance(uint64_t cycle)
{
    if (sel_pending && cycle > sel_pending_cycle) {
        mux_nodes_to(sel_pending_cycle);
        mux_connect();
        sel_pending = 0;
    }
    if (sh_pending >= 0 && adc_conv_end <= cycle) {
        mux_nodes_to(adc_conv_end);
        mux_sh_connect(sh_pending);
        sh_pending = -1;
    }
    mux_nodes_to(cycle);
}

/* select lines about to change (sel_pin_hook): the nodes up to now, the new selection once this cycle is over */
static void mux_before_select(void)
{
    mux_advance(avr->cycle);
    sel_pending = 1;
    sel_pending_cycle = avr->cycle;
}

/* ADCSRA written (after simavr's own hook, which stores it): ADEN 0 switches the ADC off, and the next conversion is
 * a first one again (25 ADC clocks, sampled at 13.5: ATmega328P datasheet, "Starting a Conversion"; simavr times it
 * so too) */
static void adcsra_write_hook(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a;
    (void)addr;
    (void)param;
    if (!(v & (1 << 7))) adc_first_conv = 1; /* ADEN */
}

static void admux_write_hook(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    mux_advance(a->cycle);
    int ch = v & 0x0F;
    if (a->cycle < adc_conv_end) sh_pending = ch; /* takes effect when the running conversion completes */
    else mux_sh_connect(ch);
    avr_core_watch_write(a, addr, v);
}

/* ADSC: the voltage the conversion samples on input src, in ADC injection units */
static uint32_t mux_sample(int src, int taxel)
{
    uint64_t now = avr->cycle;
    mux_advance(now);
    mux_sh_connect(src);
    uint8_t ps = avr->data[M328_ADCSRA] & 7;
    uint32_t adc_clk = ps ? (1u << ps) : 2u;
    double t_sample_s = (adc_first_conv ? 13.5 : 1.5) * adc_clk / avr->frequency;
    adc_conv_end = now + (uint64_t)(adc_first_conv ? 25 : 13) * adc_clk;
    adc_first_conv = 0;
    double v = mux_node_after(src, t_sample_s);
    double err = fabs(v - ideal_to(taxel, now + (uint64_t)(t_sample_s * avr->frequency))) / lsb_mv();
    if (err > mux_err_window_lsb) mux_err_window_lsb = err;
    mux_conversions++;
    if (src == 0 && mux_sel == 0) scan_first_cycle = now;
    if (src == 2 && mux_sel == 5 && scan_first_cycle) {
        double us = (double)(adc_conv_end - scan_first_cycle) * 1e6 / avr->frequency;
        if (us > scan_us_window) scan_us_window = us;
        scan_first_cycle = 0;
    }
    double units = v * ADC_UNITS_PER_MV;
    if (units < 0.0) units = 0.0;
    if (units > 65535.0) units = 65535.0;
    return (uint32_t)lround(units);
}

static void mux_after_reset(void)
{
    mux_advance(avr->cycle);
    sh_ch = 0;
    sh_mv = node_mv[0];
    sh_pending = -1;
    adc_conv_end = 0;
    adc_first_conv = 1;
    scan_first_cycle = 0;
    for (int m = 0; m < MUX_N; m++) node_cycle[m] = avr->cycle; /* the analog nodes keep their charge */
    for (int t = 0; t < N_TAXELS; t++) aa_to(t, avr->cycle);
    sel_pending = 1; /* the select pins read 0 after the reset */
    sel_pending_cycle = avr->cycle;
}

static void mux_setup(void)
{
    for (int t = 0; t < N_TAXELS; t++) taxel_ohm[t] = opt_taxel_ohm;
    for (int m = 0; m < MUX_N; m++) node_taxel[m] = m * 6; /* select 0 at power-up */
    avr->avcc = (uint32_t)(5000 * ADC_UNITS_PER_MV); /* simavr: counts = value * 1023 / avcc */
    avr_register_io_write(avr, M328_ADMUX, admux_write_hook, NULL);
    avr_register_io_write(avr, M328_ADCSRA, adcsra_write_hook, NULL); /* beside simavr's ADC (its dispatcher) */
}

static void mux_report(void)
{
    if (mux_err_window_lsb > mux_err_max_lsb) mux_err_max_lsb = mux_err_window_lsb;
    if (scan_us_window > scan_us_max) scan_us_max = scan_us_window;
    printf("MUX t=%.3f settle_err_max_lsb=%.4f settle_err_window_lsb=%.4f conversions=%llu scan_us_window=%.1f "
           "scan_us_max=%.1f\n", sim_s(), mux_err_max_lsb, mux_err_window_lsb, (unsigned long long)mux_conversions,
           scan_us_window, scan_us_max);
    mux_err_window_lsb = 0.0;
    scan_us_window = 0.0;
}

/* stdin "taxel_ohm I OHM" (I = -1: every taxel) */
static int mux_set_taxel_ohm(const char *args)
{
    int taxel;
    double ohm;
    if (sscanf(args, "%d %lf", &taxel, &ohm) != 2 || ohm < 0.0 || taxel < -1 || taxel >= N_TAXELS) return -1;
    for (int t = 0; t < N_TAXELS; t++)
        if (taxel < 0 || t == taxel) taxel_ohm[t] = ohm;
    return 0;
}

/* the waveform's next row becomes the taxels' source values (a new waveform starts here); scan_count counts
 * the scans completed, scan_row is the row the next scan converts */
static void uno_next_row(void)
{
    uint16_t *old = NULL;
    pthread_mutex_lock(&wave_lock);
    if (wave_pending) {
        old = wave;
        wave = wave_pending;
        wave_rows = wave_pending_rows;
        wave_pending = NULL;
        scan_base = (wave_pending_base >= 0 && (uint64_t)wave_pending_base <= scan_count + 1)
                        ? (uint64_t)wave_pending_base : scan_count + 1;
    }
    pthread_mutex_unlock(&wave_lock);
    free(old);
    mux_advance(avr->cycle); /* the nodes and the C_aa charged towards the old row until now */
    for (int t = 0; t < N_TAXELS; t++) {
        aa_to(t, avr->cycle);
        ideal_to(t, avr->cycle);
    }
    scan_row = ++scan_count - scan_base;
}

static void adc_trigger_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    union {
        avr_adc_mux_t mux;
        uint32_t v;
    } e = {.v = value};
    if (e.mux.kind != ADC_MUX_SINGLE) return;
    int src = e.mux.src;
    if (src > 2) return;
    int taxel = src * 6 + (mux_sel < 6 ? mux_sel : 5);
    if (!scans_running) {
        pthread_mutex_lock(&wave_lock);
        scans_running = 1;
        pthread_mutex_unlock(&wave_lock);
    }
    avr_raise_irq(adc_irq_base + ADC_IRQ_ADC0 + src, mux_sample(src, taxel));
    if (src == 2 && mux_sel == 5) uno_next_row(); /* the scan's last conversion: the taxels move on to the next row */
}

/* the sampler probe rose with the ADC off: the tick interrupt of a board that does not scan (the stream stopped; an
 * ADC interrupt runs only with the ADC on). The taxels move on to the next row as a scan's last conversion would
 * have moved them (~0.9 ms later in the tick): the rows, the waveforms' bases and the "scans" count stay ms of the
 * board's time, as the host's renderer (rigctl.simulation.hil) takes them, whether or not the board samples. */
static void uno_tick_row(void)
{
    if (!scans_running) {
        pthread_mutex_lock(&wave_lock);
        scans_running = 1;
        pthread_mutex_unlock(&wave_lock);
    }
    uno_next_row();
}

static void probe_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    int p = (int)(intptr_t)param;
    if (p == 0 && (value & 1) && !(probes_high & 1) && !(avr->data[M328_ADCSRA] & (1 << 7))) uno_tick_row();
    probes_high = (value & 1) ? (probes_high | (1 << p)) : (probes_high & ~(1 << p));
    if (value & 1) {
        probe_rise[p] = avr->cycle;
    } else if (probe_rise[p]) {
        uint64_t d = avr->cycle - probe_rise[p];
        uint64_t w = probe_rise[p] / 16000u;
        probe_total[p] += d;
        if (w != probe_window[p]) {
            if (probe_window_sum[p] > probe_window_max[p]) probe_window_max[p] = probe_window_sum[p];
            probe_window_sum[p] = 0;
            probe_window[p] = w;
        }
        probe_window_sum[p] += d;
        probe_rise[p] = 0;
    }
}

/* the encoder image's marker (PB3) rises on the tick that gives the encoder a scan's first sample: that sample is the
 * last completed scan, the waveform's row (scan_count - 1 - scan_base) mod rows; reported as "ENCSTART" */
static void encode_mark_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (!(value & 1)) return;
    pthread_mutex_lock(&wave_lock);
    unsigned long long rows = wave_rows, done = scan_count, base = scan_base;
    pthread_mutex_unlock(&wave_lock);
    long long row = rows && done > base ? (long long)((done - 1 - base) % rows) : -1;
    printf("ENCSTART t=%.6f scans=%llu row=%lld\n", sim_s(), done, row);
}

/* ================================ Uno: Timer2's missing PWM mode ================================
 * simavr 1.6's ATmega328P timer tables have no entry for waveform mode 1 (phase-correct PWM, TOP 0xFF), the mode the
 * Arduino core's init() leaves Timer2 in (for analogWrite on D3/D11, which the sketch never uses). simavr then
 * configures the timer with TOP 0 and "overflows" it every timer clock, 64 cycles: a cycle timer that fired 250,000
 * times per simulated second, raising flags nothing reads, and that cut every skip of the spinning loop (below) to 64
 * cycles. The entry is filled in before the firmware runs, as the phase-correct PWM simavr models for other cores
 * (its "fc_pwm" kind, 8 bits: an overflow every 256 timer clocks). The sketch enables no Timer2 interrupt, connects no
 * OC2A/OC2B pin and reads or writes no Timer2 register after init() (avr-objdump: no access to 0xB0-0xB6, TIMSK2 or
 * TIFR2 outside it), so it runs cycle for cycle as before: the ISR, LOAD and MUX lines and the wire bytes of a run are
 * identical. The Mega is left as it is: its sketch sets Timer2 to CTC for its tick right after init(). */
static void uno_timer2_setup(void)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next) {
        if (io->irq_ioctl_get != AVR_IOCTL_TIMER_GETIRQ('2')) continue;
        avr_timer_t *t = (avr_timer_t *)io;
        if (t->wgm_op[1].kind == avr_timer_wgm_none)
            t->wgm_op[1] = (avr_timer_wgm_t)AVR_TIMER_WGM_FCPWM8();
    }
}

static void uno_setup(void)
{
    uno_timer2_setup();
    for (int b = 4; b <= 6; b++)
        avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), b), sel_pin_hook,
                                (void *)(intptr_t)(b - 4));
    adc_irq_base = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, 0);
    avr_irq_register_notify(adc_irq_base + ADC_IRQ_OUT_TRIGGER, adc_trigger_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 0), probe_hook, (void *)0);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 1), probe_hook, (void *)1);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 2), probe_hook, (void *)2);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 3), encode_mark_hook, NULL);
    sync_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 2);
    avr_raise_irq(sync_pin, 0);
    mux_setup();
}

/* after any reset of the Uno */
static void uno_after_reset(void)
{
    /* scans count from the reset, and the playing waveform restarts at row 0 with them: a scan_base left from before
     * the reset would make scan_count - scan_base wrap around 2^64, and the rows jump (615 -> 0 for 1000 rows) once
     * the count passes the old base */
    uint16_t *old = NULL;
    pthread_mutex_lock(&wave_lock);
    if (wave_pending) { /* loaded just before the reset: the row boundary it waited for will not come */
        old = wave;
        wave = wave_pending;
        wave_rows = wave_pending_rows;
        wave_pending = NULL;
    }
    scan_count = 0;
    scan_base = 0;
    scan_row = 0;
    scans_running = 0;
    pthread_mutex_unlock(&wave_lock);
    free(old);
    mux_after_reset();
    avr_raise_irq(sync_pin, 0);
}

static void uno_poll(void)
{
    static uint64_t next_report = 16000000u;
    if (atomic_load(&sync_requests) > 0 && !sync_off_cycle) {
        atomic_fetch_sub(&sync_requests, 1);
        avr_raise_irq(sync_pin, 1);
        sync_off_cycle = avr->cycle + 16000u;
    }
    if (sync_off_cycle && avr->cycle >= sync_off_cycle) {
        avr_raise_irq(sync_pin, 0);
        sync_off_cycle = 0;
    }
    if (avr->cycle >= next_report) {
        double ticks = (double)avr->cycle / 16000.0;
        printf("ISR t=%.3f sampler_cycles_per_tick=%.1f sampler_max_per_tick=%llu tx_cycles_per_tick=%.1f "
               "tx_max_per_tick=%llu scans=%llu\n",
               sim_s(), probe_total[0] / ticks, (unsigned long long)probe_window_max[0], probe_total[1] / ticks,
               (unsigned long long)probe_window_max[1], (unsigned long long)scan_count);
        /* the encoder image's loop() work (PB2) and the CPU's load (interrupts off or encoding), per tick */
        printf("LOAD t=%.3f encoder_cycles_per_tick=%.1f encoder_max_per_tick=%llu busy_cycles_per_tick=%.1f "
               "busy_max_per_tick=%llu busy_max_since_start=%llu sp_min=%u\n", sim_s(), probe_total[2] / ticks,
               (unsigned long long)probe_window_max[2],
               busy_report_ticks ? (double)busy_report_sum / (double)busy_report_ticks : 0.0,
               (unsigned long long)busy_report_max, (unsigned long long)busy_max, sp_min);
        busy_report_sum = busy_report_ticks = busy_report_max = 0;
        mux_report();
        next_report += 16000000u;
    }
}

/* ================================ Mega: HX711, actuator, drum ================================ */
static int64_t act_steps;     /* actuator position in microsteps, + towards the sensor */
static int act_dir;
static int64_t drum_steps;
static int drum_dir;
static uint32_t index_count;
static avr_irq_t *hx_dout, *home_pin;
static int hx_ready, hx_bit;
static uint32_t hx_value;
static uint64_t hx_next_cycle;

/* ---- HX711 conversion model (Avia HX711 datasheet: "Output Data Rate and Format", "Clock Source Options") ----
 * The output data rate is 10 or 80 SPS by the RATE pin with the on-chip oscillator, whose rate the datasheet gives
 * only as "typical" (--hx711-clock-error: relative error of that oscillator, e.g. 0.05 = 5 % fast); the digital
 * filter settles 4 conversion periods after an input step (400 ms at 10 SPS, 50 ms at 80 SPS). Modelled as a
 * sinc^4 filter (four cascaded moving averages of one conversion period): each reading is the force over the last
 * four periods weighted by the cubic B-spline (group delay 2 periods), from the force sampled every 0.1 ms of
 * simulated time. DOUT goes low once per conversion period. */
#define HX_HIST 8192 /* 0.1 ms samples: 4 periods at 10 SPS with a 20 % slow oscillator fit */
static double opt_hx711_sps = 80.0;
static double opt_hx711_clock_error = 0.0;
static double hx_hist[HX_HIST];
static size_t hx_hist_pos;
static int hx_hist_primed;

static uint64_t hx711_period_cycles(void)
{
    return (uint64_t)llround(16000000.0 / (opt_hx711_sps * (1.0 + opt_hx711_clock_error)));
}

/* one force sample per mega_poll (0.1 ms of simulated time) */
static void hx711_sample(double force_g)
{
    if (!hx_hist_primed) { /* power-up: the filter starts from the force present now */
        for (size_t i = 0; i < HX_HIST; i++) hx_hist[i] = force_g;
        hx_hist_primed = 1;
    }
    hx_hist[hx_hist_pos] = force_g;
    hx_hist_pos = (hx_hist_pos + 1) % HX_HIST;
}

static double bspline4(double u) /* cubic B-spline on [0, 4], integral 1 */
{
    if (u < 0.0 || u >= 4.0) return 0.0;
    if (u >= 2.0) u = 4.0 - u;
    if (u < 1.0) return u * u * u / 6.0;
    double v = u - 1.0;
    return (1.0 + 3.0 * v + 3.0 * v * v - 3.0 * v * v * v) / 6.0;
}

/* the HX711's input noise, counts (Avia HX711 datasheet, gain 128, AVDD 5 V: 50 nV rms at 10 SPS, 90 nV at 80 SPS;
 * one count is 40 mV / 2^24 = 2.38 nV): Gaussian (Box-Muller) from a fixed-seed xorshift, so runs repeat */
static double hx711_noise(void)
{
    static uint64_t state = 0x9E3779B97F4A7C15ull;
    double u[2];
    for (int i = 0; i < 2; i++) {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        u[i] = ((double)(state >> 11) + 0.5) / 9007199254740992.0;
    }
    double rms_counts = (opt_hx711_sps < 40.0 ? 50.0 : 90.0) / (40e6 / 16777216.0);
    return rms_counts * sqrt(-2.0 * log(u[0])) * cos(2.0 * M_PI * u[1]);
}

/* the reading of the conversion that ends now: the sinc^4-weighted force of the last four periods */
static double hx711_filtered_g(void)
{
    double period_samples = (double)hx711_period_cycles() / 1600.0;
    size_t n = (size_t)ceil(4.0 * period_samples);
    if (n > HX_HIST) n = HX_HIST;
    double sum = 0.0, wsum = 0.0;
    for (size_t i = 0; i < n; i++) {
        double w = bspline4((i + 0.5) / period_samples);
        sum += w * hx_hist[(hx_hist_pos + HX_HIST - 1 - i) % HX_HIST];
        wsum += w;
    }
    return wsum > 0.0 ? sum / wsum : hx_hist[(hx_hist_pos + HX_HIST - 1) % HX_HIST];
}

/* ---- drum index sensor (optical/Hall, open collector, active low) on D48 = PL1 = ICP5 ----
 * It sees the REAL drum: each STEP pulse turns the drum by 1 / (steps_per_rev x the driver's microstep setting) of
 * a revolution; --drum-driver-microsteps sets that driver (default: the firmware's assumption, docs/wire-protocol.md
 * 2.6), so a misconfigured driver turns the drum at another speed than the step count says. The sensor pulls its
 * pin low for 1 ms each time the drum passes its index mark, then --index-bounce N more 0.1 ms pulses 0.1 ms apart
 * (a bouncing contact). --no-index-sensor: no index sensor fitted (pin pulled up; the speed-mark disc stays). The sensors
 * see the real drum (drum_turn_steps below), which a slip or a stall makes lag its step count. */
static int opt_index_sensor = 1;
static int opt_index_bounce = 0; /* extra short pulses after each mark (a bouncing contact / noisy edge) */
static double opt_driver_microsteps = RIGCTL_DRUM_MICROSTEPS_DEF;
static avr_irq_t *index_sensor_pin;
static int64_t index_sensor_revs; /* index marks passed (real drum) */
static uint64_t index_sensor_release_cycle;
static int index_bounces_left;
/* the speed-mark disc (RIGCTL_DRUM_MARKS_PER_REV slots) and its sensor on D19 = PD2 (INT2), 1 ms low per slot */
static avr_irq_t *mark_sensor_pin;
static int64_t mark_sensor_marks;
static uint64_t mark_sensor_release_cycle;
/* the real drum: revolutions turned (each STEP pulse turns 1 / (steps_per_rev x the driver's microsteps) of one,
 * times 1 - the slip: "drum slip F" makes it turn F less than its steps say (a slipping coupling, F = 1: a stalled,
 * blocked drum), "drum ok" ends it): drum_turn_steps / (steps_per_rev x the driver's microsteps) */
static double drum_turn_steps; /* the real drum's travel in the driver's microsteps */

static void index_sensor_setup(void)
{
    index_sensor_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('L'), 1);
    avr_raise_irq(index_sensor_pin, 1);
    mark_sensor_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 2);
    avr_raise_irq(mark_sensor_pin, 1);
}

/* called every 0.1 ms of simulated time */
static void index_sensor_poll(void)
{
    /* the real drum's revolutions (slip and stalls included) */
    double turn = drum_turn_steps / (RIGCTL_DRUM_STEPS_PER_REV_DEF * opt_driver_microsteps);
    int64_t marks = (int64_t)floor(turn * RIGCTL_DRUM_MARKS_PER_REV);
    if (marks != mark_sensor_marks) { /* a slot of the speed-mark disc passes its sensor: 1 ms low */
        mark_sensor_marks = marks;
        avr_raise_irq(mark_sensor_pin, 0);
        mark_sensor_release_cycle = avr->cycle + 16000u;
        printf("MARK t=%.6f marks=%lld drum_steps=%lld\n", sim_s(), (long long)marks, (long long)drum_steps);
    } else if (mark_sensor_release_cycle && avr->cycle >= mark_sensor_release_cycle) {
        avr_raise_irq(mark_sensor_pin, 1);
        mark_sensor_release_cycle = 0;
    }
    if (!opt_index_sensor) return;
    int64_t revs = (int64_t)floor(turn);
    if (revs != index_sensor_revs) {
        index_sensor_revs = revs;
        avr_raise_irq(index_sensor_pin, 0);
        index_sensor_release_cycle = avr->cycle + 16000u;
        index_bounces_left = opt_index_bounce;
        printf("ISENS t=%.6f revs=%lld drum_steps=%lld\n", sim_s(), (long long)revs, (long long)drum_steps);
    } else if (index_sensor_release_cycle && avr->cycle >= index_sensor_release_cycle) {
        avr_raise_irq(index_sensor_pin, 1);
        index_sensor_release_cycle = 0;
    } else if (index_bounces_left && !index_sensor_release_cycle) { /* bounce: another 0.1 ms low pulse */
        index_bounces_left--;
        avr_raise_irq(index_sensor_pin, 0);
        index_sensor_release_cycle = avr->cycle + 1600u;
    }
}

/* ---- external interrupts: simavr's level-trigger poll ----
 * simavr 1.6 models the low-level external interrupt (ISCn1:0 = 00, the reset default) "strictly": whenever an INTn
 * pin goes low it arms a cycle timer that reads the port through avr_ioctl on EVERY cycle while the pin stays low,
 * whether or not INTn is enabled in EIMSK (avr_extint.c, avr_extint_poll_level_trig). The Mega's HX711 DOUT (PE5 =
 * INT5) is low most of the time and the Uno's sync-in (PD2 = INT0) rests low, so that poll alone took ~27 % of the
 * harness's CPU (perf) and the boards simulated at 0.6-0.8x real time. Neither firmware uses a level-triggered
 * interrupt (the Mega's INT4 e-stop is any-edge, the Uno's INT0 rising-edge), but the datasheet's behaviour is kept
 * for any that does: the strict poll is on exactly for the INTn that are enabled in EIMSK with ISCn = 00
 * (ATmega2560 datasheet 15.2.1-15.2.3, ATmega328P 13.2.1-13.2.2), re-checked at every harness poll. */
#define EIMSK_ADDR 0x3D /* data-space address, both MCUs */
#define EICRA_ADDR 0x69
#define EICRB_ADDR 0x6A /* ATmega2560 only (INT4-7) */
static avr_extint_t *extint; /* the core's external-interrupt module */

/* every avr_reset turns the strict poll back on (avr_extint_reset): called at setup, after each reset the harness
 * makes and at every harness poll (a watchdog reset inside simavr is corrected within 0.1 ms) */
static void extint_poll(void)
{
    if (!extint) {
        for (avr_io_t *io = avr->io_port; io; io = io->next)
            if (!strcmp(io->kind, "extint")) extint = (avr_extint_t *)io;
        if (!extint) return;
    }
    int n_int = is_uno ? 2 : 8;
    uint8_t eimsk = avr->data[EIMSK_ADDR];
    uint16_t eicr = avr->data[EICRA_ADDR] | (is_uno ? 0 : (uint16_t)avr->data[EICRB_ADDR] << 8);
    for (int n = 0; n < n_int; n++) {
        if (!extint->eint[n].isc[1].reg) continue; /* edge-only */
        uint8_t want = ((eimsk >> n) & 1) && ((eicr >> (2 * n)) & 3) == 0;
        if (extint->eint[n].strict_lvl_trig != want) extint->eint[n].strict_lvl_trig = want;
    }
}

/* ---- Mega: safety wiring (drivers' EN, e-stop, test hang pin) ---- */
static avr_irq_t *estop_pin, *hang_pin;
static int estop_level = -1, hang_level = -1;
static uint64_t steps_disabled; /* STEP pulses while the drivers were disabled (they move nothing) */

/* EN (PH5) is active low with a pull-up on the board: enabled only while the pin is an output driven low */
static int drivers_enabled(void)
{
    avr_ioport_state_t st;
    if (atomic_load(&en_stuck_req)) return 1; /* the EN input stuck active (a shorted wire, a failed input) */
    if (avr_ioctl(avr, AVR_IOCTL_IOPORT_GETSTATE('H'), &st)) return 1;
    return ((st.ddr >> 5) & 1) && !((st.port >> 5) & 1);
}

/* drive a harness input pin to `level`: as the port's external level (simavr keeps it across the firmware's
 * PORT writes, e.g. its pull-up, which would otherwise pull the pin high until the next poll), and through the pin's
 * irq for an immediate edge (the pin-change interrupt) */
static void drive_pin(avr_irq_t *irq, char port, int bit, int level, int *last)
{
    /* simavr keeps one external mask and value per port: the pins of a port driven here (PE4 the e-stop, PE5 the
     * HX711's DOUT) are set together, each keeping the others' levels */
    static uint8_t ext_mask[26], ext_value[26];
    avr_ioport_state_t st;
    if (*last == level && avr_ioctl(avr, AVR_IOCTL_IOPORT_GETSTATE(port), &st) == 0 && ((st.pin >> bit) & 1) == level)
        return;
    int p = port - 'A';
    ext_mask[p] |= (uint8_t)(1u << bit);
    ext_value[p] = (uint8_t)((ext_value[p] & ~(1u << bit)) | ((unsigned)level << bit));
    avr_ioport_external_t ext = {.name = (unsigned long)port, .mask = ext_mask[p], .value = ext_value[p]};
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL(port), &ext);
    avr_raise_irq(irq, !level);
    avr_raise_irq(irq, level);
    *last = level;
}

static int eeprom_write_arg(const char *arg);

static void safety_poll(void)
{
    int off = atomic_exchange(&eeprom_flip_req, -1), brownout = 0;
    if (off < 0 && (off = atomic_exchange(&eeprom_corrupt_req, -1)) >= 0) brownout = 1;
    if (off >= 0) { /* from the simulation thread: simavr's EEPROM is not shared with the stdin thread */
        uint8_t b = 0;
        avr_eeprom_desc_t d = {.ee = &b, .offset = (uint16_t)off, .size = 1};
        if (avr_ioctl(avr, AVR_IOCTL_EEPROM_GET, &d) != -2) { /* simavr 1.6 returns -1 when it did it, -2 on error */
            b ^= 0x10;
            d.ee = &b;
            avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d);
            printf("OK eeprom-flip %d\n", off);
        } else {
            printf("ERR eeprom-flip %d\n", off);
        }
        if (brownout) { /* the reset comes later in this same step of the main loop, after the flip */
            atomic_store(&reset_cause_req, 4);
            atomic_store(&reset_requested, 1);
        }
    }
    if (atomic_load(&eeprom_write_pending)) { /* a record saved (a wrong calibration with a valid checksum), then a
                                               * power cycle: the firmware boots with it */
        printf("%s eeprom-write\n", eeprom_write_arg(eeprom_write_req) ? "ERR" : "OK");
        atomic_store(&eeprom_write_pending, 0);
        atomic_store(&reset_cause_req, 1);
        atomic_store(&reset_requested, 1);
    }
    drive_pin(estop_pin, 'E', 4, atomic_load(&estop_open_req) ? 1 : 0, &estop_level);
    drive_pin(hang_pin, 'A', 0, atomic_load(&hang_req) ? 1 : 0, &hang_level);
}

/* --eeprom-write OFFSET:HEXBYTES: bytes in the EEPROM before the first instruction (after the image's .eeprom
 * section): what a board that was once calibrated holds (HilRig writes the calibration record, as the simulated
 * rigs' factory calibration does) */
static int eeprom_write_arg(const char *arg)
{
    uint8_t bytes[64];
    char *end;
    long off = strtol(arg, &end, 0);
    size_t n = 0;
    if (*end != ':' || off < 0 || off > 4095) return 1;
    for (const char *h = end + 1; h[0] && h[1]; h += 2) {
        unsigned v;
        if (n >= sizeof bytes || sscanf(h, "%2x", &v) != 1) return 1;
        bytes[n++] = (uint8_t)v;
    }
    avr_eeprom_desc_t d = {.ee = bytes, .offset = (uint16_t)off, .size = (uint16_t)n};
    return !n || off + (long)n > 4096 || avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d) == -2;
}

static void safety_setup(void)
{
    estop_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 4);
    hang_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('A'), 0);
    safety_poll();
}

/* after any reset: the hang request ends with it; the pins are driven again */
static void safety_after_reset(void)
{
    atomic_store(&hang_req, 0);
    estop_level = hang_level = -1;
    safety_poll();
}

static double mega_force_g(void)
{
    double x = (double)act_steps / opt_act_steps_per_mm;
    double k_req = atomic_exchange(&spring_k_req, 0.0), f;
    if (k_req > 0.0) {
        /* the stiffness changes: off the contact a plate swap (the new plate's surface where the rig's is); under
         * load the force is continuous (a plate cannot be swapped while pressed; a soft layer bottoming out, a mount
         * settling change how the force grows with further travel): the spring's zero moves so the force stays */
        double k_old = atomic_load(&opt_spring_k);
        opt_contact_mm = x > opt_contact_mm ? x - (x - opt_contact_mm) * k_old / k_req : opt_contact_mm0;
        atomic_store(&opt_spring_k, k_req);
    }
    f = x > opt_contact_mm ? atomic_load(&opt_spring_k) * (x - opt_contact_mm) : 0.0;
    return f + atomic_load(&bump_g_x1000) / 1000.0;
}

/* drive the home switch (PH4, closed = low at x <= 0) as the port's external level (drive_pin): the firmware's writes
 * to PORTH (DIR on PH3 at every actuator step, EN on PH5, the index output on PH6, the pull-up on PH4) used to raise
 * this pin's irq with the pull-up's level, so a closed switch read open until the next poll (HOME's direction proof
 * saw the switch open while a reversed motor drove into the rear stop) */
static int home_level = -1;
static void update_home(void)
{
    int closed = atomic_load(&home_stuck_req) || (act_steps <= 0 && !atomic_load(&home_broken_req));
    drive_pin(home_pin, 'H', 4, closed ? 0 : 1, &home_level);
}

/* the direction (1 = towards the sensor, as the motor really turns) and time of the last actuator step that moved */
static int act_last_dir = -1;
static double act_last_t;
/* a slipping coupling ("coupling slip F"): the steps it did not pass on wind it up (act_windup) and it catches up at
 * once when the motor has held still for ACT_CATCHUP_MS (the screw jumps); lost steps ("steps lost F") never return */
#define ACT_CATCHUP_MS 20.0
static double act_slip_acc, act_lost_acc;
static int64_t act_windup;
static uint64_t act_step_last_cycle;

static void act_step_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value & 1) {
        if (!drivers_enabled()) {
            steps_disabled++;
            return;
        }
        int fwd = act_dir ^ atomic_load(&act_reversed_req); /* a swapped coil pair turns the motor the other way */
        double t = sim_s();
        if (act_last_dir >= 0 && fwd != act_last_dir) /* the first step of a new direction, and the last of the old */
            printf("AREV t=%.6f dir=%d last_t=%.6f act_steps=%lld\n", t, fwd, act_last_t, (long long)act_steps);
        if (atomic_load(&rxlog_req)) printf("ASTEP t=%.6f dir=%d\n", t, fwd);
        act_last_dir = fwd;
        act_last_t = t;
        if (!fwd && act_steps <= -(int64_t)llround(opt_rear_stop_mm * opt_act_steps_per_mm))
            return; /* against the rear stop: the motor stalls, the firmware's step count goes on */
        if (fwd && opt_stall_g > 0.0) { /* the stall: the spring's force one step further (as mega_force_g) */
            double x = (double)(act_steps + 1) / opt_act_steps_per_mm;
            if (x > opt_contact_mm && atomic_load(&opt_spring_k) * (x - opt_contact_mm) > opt_stall_g) {
                return; /* lost: the firmware's step count goes on */
            }
        }
        double slip = atomic_load(&act_slip_req), lost = atomic_load(&act_lost_req);
        act_step_last_cycle = avr->cycle;
        if (slip > 0.0 || lost > 0.0) {
            act_slip_acc += slip;
            act_lost_acc += lost;
            if (act_lost_acc >= 1.0) { /* lost for good: the motor skipped it */
                act_lost_acc -= 1.0;
                return;
            }
            if (act_slip_acc >= 1.0) { /* the coupling winds up: the screw stays, the motor turned */
                act_slip_acc -= 1.0;
                act_windup += fwd ? 1 : -1;
                return;
            }
        }
        act_steps += fwd ? 1 : -1;
        update_home();
    }
}

static void act_dir_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    act_dir = value & 1;
}

static void drum_step_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (!(value & 1)) return;
    if (!drivers_enabled()) {
        steps_disabled++;
        return;
    }
    drum_steps += drum_dir ? 1 : -1;
    drum_turn_steps += (drum_dir ^ atomic_load(&drum_reversed_req) ? 1.0 : -1.0) *
                       (1.0 - atomic_load(&drum_slip_req)); /* exact without slip */
}

static void drum_dir_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    drum_dir = value & 1;
}

static void index_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value & 1) {
        index_count++;
        printf("IDX t=%.6f n=%u drum_steps=%lld\n", sim_s(), index_count, (long long)drum_steps);
    }
}

/* DOUT driven as the port's external level (drive_pin): the firmware's pull-up on PE5 (issue 55) and its writes to
 * PORTE (the actuator's STEP on PE3, the e-stop's pull-up on PE4) would otherwise pull it high until the next edge */
static int hx_dout_level = -1;
static void hx_dout_set(int level)
{
    drive_pin(hx_dout, 'E', 5, level, &hx_dout_level);
}

static void hx_sck_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (atomic_load(&hx_sck_broken_req)) { /* the wire is broken: the HX711 sees no clock, DOUT stays low */
        if (hx_ready) hx_dout_set(0);
        return;
    }
    if (!(value & 1) || !hx_ready) return; /* shift on rising edges while a reading is out */
    if (hx_bit < 24) {
        int bit = (hx_value >> (23 - hx_bit)) & 1;
        double p = atomic_load(&hx_dout_noise_req);
        if (p > 0.0) { /* noise on the DOUT line: the bit the MCU samples flips with probability p */
            static uint64_t st = 0x2545F4914F6CDD1Dull;
            st ^= st << 13;
            st ^= st >> 7;
            st ^= st << 17;
            if ((double)(st >> 11) / 9007199254740992.0 < p) bit ^= 1;
        }
        hx_dout_set(bit);
        hx_bit++;
    } else { /* 25th clock: gain 128, DOUT high until the next conversion */
        hx_dout_set(1);
        hx_ready = 0;
        hx_bit = 0;
    }
}

/* after a reset of the MCU the pins the harness drives are driven again (avr_reset clears the port state). The HX711
 * is another chip on the same supply: an external, brown-out or watchdog reset of the MCU leaves it converting on its
 * own schedule (Avia HX711 datasheet: it powers down only when PD_SCK stays high for over 60 us), so a reading it
 * finished stays ready with DOUT low through the reset and the bootloader's wait, and the firmware's first reading
 * may be one that waited; a reading being shifted out when the MCU reset is abandoned (DOUT high until the next
 * conversion). A power-on ("poweron") starts its conversions afresh with the MCU's. */
static int hx_power_cycle; /* the next mega_after_reset is a power-on */

static void mega_after_reset(void)
{
    if (!hx_dout) return;
    hx_dout_level = -1; /* driven again for the reset port */
    if (hx_power_cycle || hx_bit > 0) {
        hx_ready = 0;
        hx_bit = 0;
        hx_dout_set(1);
        if (hx_power_cycle) hx_next_cycle = avr->cycle + hx711_period_cycles();
    } else if (hx_ready) { /* a finished reading waits: DOUT low */
        hx_dout_set(0);
    } else {
        hx_dout_set(1);
    }
    hx_power_cycle = 0;
    update_home();
    avr_raise_irq(index_sensor_pin, 0); /* the sensor's level is driven again after the port reset */
    avr_raise_irq(index_sensor_pin, index_sensor_release_cycle ? 0 : 1);
    avr_raise_irq(mark_sensor_pin, 0);
    avr_raise_irq(mark_sensor_pin, mark_sensor_release_cycle ? 0 : 1);
    safety_after_reset();
}

/* EEPROM writes (EECR with EEPE set: avr-libc's eeprom_write/update after EEMPE), counted for the wear tests ("TEL
 * ... ee_writes=N"); simavr's EEPROM module keeps its own handler on EECR (io writes are dispatched to both) */
#define M2560_EECR 0x3F
static unsigned long long ee_writes;

static void eecr_write_hook(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a, (void)addr, (void)param;
    if (v & (1 << 1)) ee_writes++;
}

static void mega_setup(void)
{
    hx_dout = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 5);
    home_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('H'), 4);
    hx_dout_set(1);
    update_home();
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('G'), 5), hx_sck_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('E'), 3), act_step_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('H'), 3), act_dir_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 5), drum_step_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 4), drum_dir_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('H'), 6), index_hook, NULL);
    avr_register_io_write(avr, M2560_EECR, eecr_write_hook, NULL);
    hx_next_cycle = hx711_period_cycles();
    index_sensor_setup();
    safety_setup();
}

/* --state-addr ADDR: the data-space address of the controller's state byte (mega_drum.cpp's ctl.state): each change
 * is reported ("STATE t=... state=N") with a TEL line at that instant, from the MCU's own RAM, so a host judges the
 * latch's time and place from the controller's truth, not from its polls */
static int opt_state_addr = -1;
static int state_seen = -1;
static double force_max_g = -1e300, act_max_mm = -1e300; /* the largest since the last TEL line */
/* the actuator motor's position as the screw travel it turns (the screw's plus the coupling's wind-up: only the
 * motor's real steps move it, a catch-up moves the screw and not it), the furthest since the last TEL line: the truth
 * log's motor_mm, what the campaign's step-after-latch judge reads */
static double motor_max_mm = -1e300;

static double motor_mm(void)
{
    return (double)(act_steps + act_windup) / opt_act_steps_per_mm;
}

static void print_tel(void)
{
    double f = mega_force_g(), x = act_steps / opt_act_steps_per_mm, m = motor_mm();
    if (f > force_max_g) force_max_g = f;
    if (x > act_max_mm) act_max_mm = x;
    if (m > motor_max_mm) motor_max_mm = m;
    printf("TEL t=%.6f cycle=%llu drum_steps=%lld drum_dir=%d act_steps=%lld act_mm=%.4f force_g=%.3f "
           "index=%u en=%d steps_disabled=%llu drum_turn=%.5f ee_writes=%llu force_max_g=%.3f act_max_mm=%.4f "
           "motor_max_mm=%.4f\n",
           sim_s(), (unsigned long long)avr->cycle, (long long)drum_steps, drum_dir, (long long)act_steps, x, f,
           index_count, drivers_enabled(), (unsigned long long)steps_disabled,
           drum_turn_steps / (RIGCTL_DRUM_STEPS_PER_REV_DEF * opt_driver_microsteps), ee_writes, force_max_g,
           act_max_mm, motor_max_mm);
    force_max_g = act_max_mm = motor_max_mm = -1e300;
}

static void mega_poll(void)
{
    static uint64_t next_tel;
    int rate = atomic_exchange(&hx_rate_req, 0);
    if (rate) { /* the RATE pin changed: the board powered on again with it (the HX711 too) */
        opt_hx711_sps = rate;
        atomic_store(&reset_cause_req, 1);
        atomic_store(&reset_requested, 1);
    }
    if (act_windup && avr->cycle - act_step_last_cycle > (uint64_t)(ACT_CATCHUP_MS * 16000.0)) {
        int64_t to = act_steps + act_windup; /* the coupling catches up: the screw jumps */
        if (act_windup > 0 && opt_stall_g > 0.0) { /* the motor drives the catch-up: no further than its stall */
            int64_t stall = (int64_t)floor((opt_contact_mm + opt_stall_g / atomic_load(&opt_spring_k)) *
                                           opt_act_steps_per_mm);
            if (to > stall) to = stall > act_steps ? stall : act_steps;
        }
        act_steps = to;
        act_windup = 0;
        update_home();
    }
    update_home();
    safety_poll();
    index_sensor_poll();
    double f_now = mega_force_g(), x_now = act_steps / opt_act_steps_per_mm, m_now = motor_mm();
    if (f_now > force_max_g) force_max_g = f_now;
    if (x_now > act_max_mm) act_max_mm = x_now;
    if (m_now > motor_max_mm) motor_max_mm = m_now;
    hx711_sample(f_now);
    if (avr->cycle >= hx_next_cycle) { /* end of a conversion period: DOUT low = ready */
        hx_next_cycle += hx711_period_cycles();
        if (!hx_ready) {
            double f = hx711_filtered_g();
            long raw = opt_loadcell_offset + lround((f * atomic_load(&cell_gain_req) + atomic_load(&cell_offset_g_req)) *
                                                    opt_counts_per_g * atomic_load(&polarity_req) + hx711_noise());
            if (raw > 0x7FFFFF) raw = 0x7FFFFF;
            if (raw < -0x800000) raw = -0x800000;
            if (!atomic_load(&hx_frozen_req)) hx_value = (uint32_t)raw & 0xFFFFFFu; /* frozen: the last value again */
            hx_ready = 1;
            hx_bit = 0;
            hx_dout_set(0);
        }
    }
    if (opt_state_addr >= 0 && opt_state_addr < (int)avr->ramend) {
        int state = avr->data[opt_state_addr];
        if (state != state_seen) {
            state_seen = state;
            printf("STATE t=%.6f state=%d\n", sim_s(), state);
            print_tel(); /* the truth where the state changed */
            next_tel = avr->cycle + (uint64_t)(opt_tel_ms * 16000.0);
        }
    }
    if (avr->cycle >= next_tel) {
        next_tel = avr->cycle + (uint64_t)(opt_tel_ms * 16000.0);
        print_tel();
    }
}

/* ================================ clock lock ================================ */
/* --clock-lock FILE: two harnesses (one per board) given the same file run in lock step on simulated time: each
 * publishes its simulated time (its own slot: mega 0, uno 1; ns, monotonic across resets, a hold in reset counts
 * as simulated time too) and waits while it is more than LOCK_LEAD_S ahead of the other's. Each is paced to the wall
 * clock (or not: --no-pace), but on a starved host they fall behind it at different rates (the Uno streams and
 * samples more per ms): locked, a ms of the Uno's time is a ms of the Mega's, so what the host renders from the
 * Mega's drum travel plays at the drum's speed. A partner that has not published yet, or whose time has not moved for
 * LOCK_STALE_S of wall time (stopped, exited), is not waited for.
 * Slot 2 is the host's grant (rigctl.core.shared_clock, docs/architecture.md "Time on a simulated rig"): ns + 1 of
 * simulated time the boards may run to (0: no grant, as before: not waited for). The host moves it on as it lives
 * (its reads, writes, waits and a heartbeat), a bounded lead past its last sign of life; a core that reaches it
 * waits, so a starved host pauses both boards instead of looking silent to them. The grant is never stale: a host
 * that stopped granting is one the boards wait for (its process gone, the harness exits on its own).
 * Slots 3 and 4 are the host's writes to the Mega's and the Uno's port: CLOCK_MONOTONIC ns + 1 of the moment it began
 * its last one (rigctl.simulation.hil_clock, stamped before the write). Slots 5 and 6 count the bytes each harness has
 * read from its pty (this harness writes its own), slots 7 and 8 the bytes the host's stamped writes to each port
 * will have brought once they are all read (the host writes them, before the stamp). A pty hands a writer's bytes on
 * through a kernel worker, which a loaded machine holds back for up to ~1 s, and may hand on two writes made one
 * after the other in two pushes a second apart; a board that has read fewer bytes than its host's stamped writes
 * bring, with nothing of the host's left in the bridge, waits for the rest (--host-write-hold-s bounds the wait from
 * the last stamp, wall clock: a write that failed is no write), as it waits for the grant: a request on its way is
 * not a silent host (the firmware's watchdog), and a window's speed on its way is not late (the Uno encoder). Counted,
 * not timed: a read of an earlier write's bytes after the stamp is not the stamped write's arrival. The virtual Mega
 * does the same (rigctl.simulation.virtual_mega: request_on_its_way). */
#define LOCK_LEAD_S 0.002
#define LOCK_STALE_S 0.5
#define LOCK_WAIT_MIN_S 0.0001
#define LOCK_WAIT_MAX_S 0.002
#define LOCK_SLOTS 11 /* mega, uno, the host's grant, its last write to the Mega's port and the Uno's, the bytes
                        * read from each port, the bytes the host's stamped writes bring to each, when each harness
                        * last wrote to its port (CLOCK_MONOTONIC ns + 1: the host judges its bytes on their way) */
#define RX_SLOT(uno) (5 + (uno))
#define TARGET_SLOT(uno) (7 + (uno))
#define TX_SLOT(uno) (9 + (uno))
static _Atomic uint64_t *lock_slots;
static int lock_self;
static double lock_time_s;       /* this core's simulated time for the lock */
static uint64_t lock_cycle;      /* avr->cycle at the last update */
static uint64_t lock_other_ns;   /* the partner's last published time ... */
static double lock_other_wall;   /* ... and when it last changed (wall) */
static double opt_host_write_hold_s = 2.0; /* --host-write-hold-s: longest wait for a stamped write's bytes, s (wall) */

static void clock_lock_open(const char *path, int slot)
{
    int fd = open(path, O_RDWR | O_CREAT, 0600);
    struct stat st;
    if (fd < 0 || fstat(fd, &st) < 0 || (st.st_size < (off_t)(LOCK_SLOTS * sizeof(uint64_t))
                                          && ftruncate(fd, LOCK_SLOTS * sizeof(uint64_t)) < 0)) {
        fprintf(stderr, "cannot open the clock-lock file %s: %s\n", path, strerror(errno));
        exit(2);
    }
    void *m = mmap(NULL, LOCK_SLOTS * sizeof(uint64_t), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (m == MAP_FAILED) {
        fprintf(stderr, "cannot map the clock-lock file %s: %s\n", path, strerror(errno));
        exit(2);
    }
    lock_slots = m;
    lock_self = slot;
    lock_other_wall = now_s();
    rx_total += atomic_load(&lock_slots[RX_SLOT(slot)]); /* a harness started again on the same file counts on */
    atomic_store(&lock_slots[RX_SLOT(slot)], rx_total);
}

/* the bridge handed bytes of the board to the pty now: the host's waits take them as on their way until it finds
 * bytes there after this (rigctl.simulation.hil_clock: in_flight) */
static void tx_stamp(void)
{
    struct timespec ts;
    if (!lock_slots) return;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    atomic_store(&lock_slots[TX_SLOT(is_uno ? 1 : 0)], (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec + 1);
}

static void rx_count(ssize_t r)
{
    rx_total += (uint64_t)r;
    if (lock_slots) atomic_store(&lock_slots[RX_SLOT(is_uno ? 1 : 0)], rx_total);
}

static void clock_lock_publish(double extra_s)
{
    uint64_t c = avr->cycle;
    lock_time_s += (c >= lock_cycle ? c - lock_cycle : c) / (double)avr->frequency + extra_s; /* c < last: reset */
    lock_cycle = c;
    atomic_store(&lock_slots[lock_self], (uint64_t)(lock_time_s * 1e9) + 1); /* 0 = not started */
}

/* how far this core may run past its simulated time before it must wait for the host's grant, s (+inf: no grant) */
static double host_grant_room_s(void)
{
    uint64_t grant = lock_slots ? atomic_load(&lock_slots[2]) : 0;
    if (grant == 0) return INFINITY;
    return (double)(grant - 1) * 1e-9 - lock_time_s;
}

/* wait while the core has reached the host's grant (a starved host: the whole simulated world pauses). Returns the
 * wall seconds it waited (0: it did not). */
static double host_grant_wait(void)
{
    double t0 = 0.0, waited = 0.0;
    while (host_grant_room_s() <= 0.0 && !atomic_load(&quit_requested)) {
        if (t0 == 0.0) t0 = now_s();
        struct timespec ts = {0, 200000}; /* 0.2 ms: the host's heartbeat grants every few ms */
        nanosleep(&ts, NULL);
        waited = now_s() - t0;
    }
    return waited;
}

/* wait while the host's stamped writes to this board's port are on their way (fewer bytes read than slot 7 + is_uno
 * says they bring, nothing of the host's left in the bridge, the link up, the last stamp, slot 3 + is_uno, no more
 * than --host-write-hold-s ago): the pty is polled meanwhile and the bridge takes the bytes at once.
 * Returns the wall seconds it waited (0: it did not). */
static double host_write_wait(void)
{
    if (!lock_slots || atomic_load(&link_down_req)) return 0.0;
    double t0 = 0.0, waited = 0.0;
    for (;;) {
        uint64_t stamp = atomic_load(&lock_slots[3 + (is_uno ? 1 : 0)]);
        uint64_t target = atomic_load(&lock_slots[TARGET_SLOT(is_uno ? 1 : 0)]);
        if (stamp == 0 || target <= rx_total || rx_pos != rx_len || atomic_load(&quit_requested)) break;
        double t = now_s();
        if (t - (double)(stamp - 1) * 1e-9 > opt_host_write_hold_s) break; /* a write that failed: no write */
        if (t0 == 0.0) t0 = t;
        struct pollfd pfd = {.fd = pty_master, .events = POLLIN};
        int ready = poll(&pfd, 1, 1) > 0 && (pfd.revents & POLLIN);
        if (ready) bridge_poll(1);
        waited = now_s() - t0;
    }
    return waited;
}

static void clock_lock_wait(void)
{
    for (;;) {
        uint64_t other = atomic_load(&lock_slots[!lock_self]);
        double t = now_s();
        if (other != lock_other_ns) {
            lock_other_ns = other;
            lock_other_wall = t;
        }
        double excess = lock_time_s - ((other - 1) * 1e-9 + LOCK_LEAD_S);
        if (other == 0 || excess <= 0.0 || t - lock_other_wall > LOCK_STALE_S || atomic_load(&quit_requested))
            return;
        /* the partner moves at about wall-clock pace: sleep until it has caught up by the excess and half the lead
         * (LOCK_WAIT_MIN_S .. LOCK_WAIT_MAX_S), not in 0.1 ms steps (each a context switch: ~3000 a second) */
        double wait = excess + LOCK_LEAD_S / 2;
        if (wait < LOCK_WAIT_MIN_S) wait = LOCK_WAIT_MIN_S;
        if (wait > LOCK_WAIT_MAX_S) wait = LOCK_WAIT_MAX_S;
        struct timespec ts = {0, (long)(wait * 1e9)};
        nanosleep(&ts, NULL);
    }
}

/* ================================ a sleeping core ================================
 * The Mega's loop() sleeps (SLEEP, idle mode) until an interrupt. simavr then skips the core's time to its next cycle
 * timer and, in raw mode, usleeps that time itself (sim_avr.c avr_callback_sleep_raw). This harness paces the core to
 * the wall clock on its own (below, and --no-pace runs it as fast as it can) and polls its models (pty, HX711, index
 * sensor, e-stop, ...) every 0.1 ms of simulated time: the sleep callback does nothing, and a cycle timer every 0.1 ms
 * bounds a sleeping core's skips to a poll period, so the models see the same time steps as with an awake core. An
 * avr_reset (the harness's, or the watchdog's inside simavr) clears the cycle timers: each poll re-arms it. */
#define POLL_CYCLES 1600 /* 0.1 ms at 16 MHz */
#define POLL_WALL_S 0.0001 /* paced: the pty and the open detector are asked at most this often (wall clock) ... */
#define PACE_AHEAD_UNO_S 0.001 /* ... and the core sleeps when this far ahead of the wall clock (its bytes' pace) */
#define PACE_AHEAD_MEGA_S 0.002 /* (a host request wakes the sleeping harness: the Mega's replies are not later) */
static void sleep_paced_by_harness(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    (void)how_long;
}

static avr_cycle_count_t poll_period_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)param;
    return when + POLL_CYCLES;
}

static void poll_period_arm(void)
{
    if (!avr_cycle_timer_status(avr, poll_period_timer, NULL))
        avr_cycle_timer_register(avr, POLL_CYCLES, poll_period_timer, NULL);
}

/* ================================ a spinning core ================================
 * A loop() that polls (the Uno's: it reads UCSR0A and its receive ring until an interrupt brings work) runs the same
 * few instructions over and over; each costs the harness as much as any other, and on the Uno they were ~43 % of all
 * instructions (the rest: its interrupts). When the core comes back to a loop head with the same registers, SREG and
 * SP as on its previous pass there, P cycles later, and that pass wrote nothing (no store, push, call, OUT/SBI/CBI,
 * SLEEP/WDR/SPM, SEI/CLI, RET/RETI) and read no I/O register whose read has a side effect in simavr (a read hook; the
 * UART status register's is allowed: it only re-raises XON while the receive FIFO is empty), and no interrupt is
 * pending that the core would take, then every following pass is the very same until an event changes memory or an
 * I/O register: a cycle timer (a timer, the ADC, the UART, the watchdog, the poll-period bound) or the harness's
 * 0.1 ms poll (pins and bytes it drives). The harness then moves avr->cycle on by the whole passes that end before the next of those events: the
 * core is at the same instruction with the same state at the same cycle as if it had run them, so the instruction
 * that reaches the event, the interrupt it takes and everything after are cycle for cycle those of the busy loop
 * (its PC and registers are unchanged, and no pass skipped could have seen anything new). Streaming, the Uno's loop()
 * gets ~41 % of its cycles (its interrupts the rest); optiboot's wait for a byte (interrupts off) qualifies too. The
 * tracking costs every instruction a little, so it runs for the Uno only: the Mega's loop() sleeps (SLEEP) and feeds
 * the watchdog (WDR), and its bootloader's wait counts, so neither ever qualifies (measured: 15 % more CPU for the
 * Mega, none saved). The EXIT line counts the skips ("spin_skips=N"). */
#define SPIN_MAX_PASS 32 /* instructions in one pass at most */
#define SPIN_MAX_BACK 256 /* bytes of a backward jump that starts a candidate loop */
#define SPIN_MISSES 2
#define SPIN_BAN_STEPS 100000
#define UCSR0A_ADDR 0xC0 /* data-space address, ATmega328P and ATmega2560 */
static uint32_t spin_head = UINT32_MAX; /* candidate loop head (byte address) */
static int spin_dirty, spin_len, spin_have;
static uint8_t spin_state[32 + 8 + 2]; /* registers, SREG, SP at the last arrival at the head ... */
static uint64_t spin_cycle;            /* ... and its cycle */
static int spin_misses;                /* pure passes in a row whose state changed (a counting loop, a division) */
static uint64_t spin_steps;            /* steps tracked */
static struct {
    uint32_t head;
    uint64_t until; /* spin_steps */
} spin_ban[64]; /* heads of such loops, not taken as candidates for SPIN_BAN_STEPS */
static uint64_t spin_skips;

static void spin_snapshot(uint8_t *out)
{
    memcpy(out, avr->data, 32);
    memcpy(out + 32, avr->sreg, 8);
    out[40] = avr->data[0x5D];
    out[41] = avr->data[0x5E];
}

/* a read of data address addr has no side effect in simavr (SRAM, an I/O register without a read hook, or the UART
 * status register) */
static int spin_read_ok(uint32_t addr)
{
    if (addr < 32 || addr >= 32 + MAX_IOs) return 1;
    avr_io_read_t hook = avr->io[AVR_DATA_TO_IO(addr)].r.c;
    return !hook || hook == avr->io[AVR_DATA_TO_IO(UCSR0A_ADDR)].r.c;
}

/* the instruction at pc, about to run with the registers as they are now, writes nothing and reads no I/O register
 * with a side effect */
static int spin_pure(uint32_t pc)
{
    uint16_t op = avr->flash[pc] | (avr->flash[pc + 1] << 8);
    const uint8_t *r = avr->data;
    if ((op & 0xFE00) == 0x9200) return 0;                   /* STS, ST X/Y/Z +/-, XCH/LAS/LAC/LAT, PUSH */
    if ((op & 0xD200) == 0x8200) return 0;                   /* ST/STD Y+q, Z+q */
    if ((op & 0xF800) == 0xB800) return 0;                   /* OUT */
    if ((op & 0xFD00) == 0x9800) return 0;                   /* CBI, SBI */
    if ((op & 0xF000) == 0xD000) return 0;                   /* RCALL */
    if ((op & 0xFE0E) == 0x940E) return 0;                   /* CALL */
    if ((op & 0xFF0F) == 0x9408) return 0;                   /* BSET/BCLR: SEI, CLI, ... */
    if ((op & 0xFF0F) == 0x9508 || (op & 0xFF0F) == 0x9509) return 0; /* RET, RETI, ICALL, EICALL, SLEEP, WDR, SPM... */
    if ((op & 0xFE0F) == 0x900F) return 0;                   /* POP */
    if ((op & 0xF800) == 0xB000) return spin_read_ok(32 + ((op & 0x0F) | ((op >> 5) & 0x30))); /* IN */
    if ((op & 0xFD00) == 0x9900) return spin_read_ok(32 + ((op >> 3) & 0x1F));                /* SBIC, SBIS */
    if ((op & 0xFE0F) == 0x9000) return spin_read_ok(avr->flash[pc + 2] | (avr->flash[pc + 3] << 8)); /* LDS */
    if ((op & 0xD200) == 0x8000) { /* LD/LDD Y+q, Z+q */
        uint32_t q = (op & 7) | ((op >> 7) & 0x18) | ((op >> 8) & 0x20);
        uint32_t base = (op & 8) ? (r[28] | (r[29] << 8)) : (r[30] | (r[31] << 8));
        return spin_read_ok(base + q);
    }
    if ((op & 0xFE00) == 0x9000) { /* LD X/Y/Z with pre-decrement or post-increment; LPM/ELPM (flash) */
        switch (op & 0x0F) {
        case 0x1: case 0x2: return spin_read_ok(r[30] | (r[31] << 8));
        case 0x9: case 0xA: return spin_read_ok(r[28] | (r[29] << 8));
        case 0xC: case 0xD: case 0xE: return spin_read_ok(r[26] | (r[27] << 8));
        default: return 1;
        }
    }
    return 1;
}

/* the cycle of the next cycle timer (simavr's list), or UINT64_MAX */
static uint64_t spin_next_timer(void)
{
    uint64_t when = UINT64_MAX;
    for (avr_cycle_timer_slot_p t = avr->cycle_timers.timer; t; t = t->next)
        if (t->when < when) when = t->when;
    return when;
}

/* after a step the core ran (pc_before: the instruction it ran; pure: spin_pure of it, before it ran): track the
 * candidate loop and skip the passes that would repeat themselves before the next event (next_check: the harness's
 * next poll) */
static void spin_step(uint32_t pc_before, int pure, uint64_t next_check)
{
    uint32_t pc = avr->pc;
    if (!pure) spin_dirty = 1;
    spin_steps++;
    if (pc == spin_head) {
        uint8_t now[sizeof spin_state];
        spin_snapshot(now);
        uint64_t pass = avr->cycle - spin_cycle;
        if (spin_have && !spin_dirty && (!avr->sreg[S_I] || avr->interrupt_state == 0) && avr->state == cpu_Running
            && pass > 0 && !memcmp(now, spin_state, sizeof now)) {
            uint64_t event = spin_next_timer();
            if (next_check < event) event = next_check;
            if (event != UINT64_MAX && event > avr->cycle + pass) {
                avr->cycle += (event - 1 - avr->cycle) / pass * pass; /* whole passes, all ending before the event */
                spin_skips++;
            }
            spin_misses = 0;
        } else {
            /* a loop whose pure passes keep changing its registers (a delay loop, a division) never repeats a pass:
             * after SPIN_MISSES of them its head is no candidate for SPIN_BAN_STEPS steps (decoding and comparing
             * its passes cost more than they would find) */
            spin_misses = spin_have && !spin_dirty ? spin_misses + 1 : 0;
            if (spin_misses >= SPIN_MISSES) {
                spin_ban[(pc >> 1) & 63].head = pc;
                spin_ban[(pc >> 1) & 63].until = spin_steps + SPIN_BAN_STEPS;
                spin_misses = 0;
                spin_head = UINT32_MAX;
                spin_have = 0;
                return;
            }
            memcpy(spin_state, now, sizeof now);
            spin_have = 1;
        }
        spin_cycle = avr->cycle;
        spin_dirty = 0;
        spin_len = 0;
    } else if (pc < pc_before && pc_before - pc <= SPIN_MAX_BACK /* a backward jump: a new candidate loop */
               && !(spin_ban[(pc >> 1) & 63].head == pc && spin_steps < spin_ban[(pc >> 1) & 63].until)) {
        spin_misses = 0;
        spin_head = pc;
        spin_snapshot(spin_state);
        spin_cycle = avr->cycle;
        spin_have = 1;
        spin_dirty = 0;
        spin_len = 0;
    } else if (++spin_len > SPIN_MAX_PASS) {
        spin_head = UINT32_MAX;
        spin_have = 0;
    }
}

/* ================================ one step of the core ================================
 * What simavr 1.6's avr_run does for a core without gdb (avr_callback_run_raw, sim_avr.c): the instruction
 * (avr_run_one), the cycle timers that are due (avr_cycle_timer_process, which also notes in run_cycle_count how far
 * the next one is), the new PC, a sleeping core's skip to the next timer (avr->sleep, then the cycles), pending
 * interrupts. Most steps find no timer due (the list's first, the earliest, is later): that case runs inline here,
 * with the same effects (run_cycle_count set as simavr sets it), instead of through three calls into the library
 * (avr_run, avr->run, avr_cycle_timer_process: ~15 % of the Uno harness's instructions). Every other case is
 * simavr's own sequence, step for step. Whenever avr->run is not avr_callback_run_raw, simavr's own avr_run runs the
 * step: its watchdog resets the MCU by swapping avr->run for a callback that resets it on the next step. */
static int core_step(void)
{
    if (avr->run != avr_callback_run_raw) return avr_run(avr);
    avr_flashaddr_t new_pc = avr->pc;
    if (avr->state == cpu_Running) new_pc = avr_run_one(avr);
    avr_cycle_timer_slot_p first = avr->cycle_timers.timer;
    if (avr->state == cpu_Running && first && avr->cycle < first->when) { /* no timer due */
        avr_cycle_count_t ahead = first->when - avr->cycle;
        if (ahead > avr->run_cycle_limit) ahead = avr->run_cycle_limit;
        avr->run_cycle_count = ahead ? ahead : 1;
        avr->pc = new_pc;
        if (avr->interrupt_state) avr_service_interrupts(avr);
        return avr->state;
    }
    avr_cycle_count_t sleep = avr_cycle_timer_process(avr);
    avr->pc = new_pc;
    if (avr->state == cpu_Sleeping) {
        if (!avr->sreg[S_I]) { /* sleeping with interrupts off: simavr stops the core */
            avr->state = cpu_Done;
            return avr->state;
        }
        avr->sleep(avr, sleep);
        avr->cycle += 1 + sleep;
    }
    if ((avr->state == cpu_Running || avr->state == cpu_Sleeping) && avr->interrupt_state)
        avr_service_interrupts(avr);
    return avr->state;
}

/* ================================ main loop ================================ */
static void usage(void)
{
    fprintf(stderr, "usage: rigctl_simavr --board uno|mega [--no-pace] [--reset-on-open] [--boot-ms MS] [--bootloader HEX] "
                    "[--wave FILE] [--spring-k G_PER_MM] [--contact-mm MM] [--act-steps-per-mm N] "
                    "[--counts-per-g N] [--loadcell-offset N] [--rear-stop-mm MM] [--tel-ms MS] [--max-seconds S] [--clock-lock FILE] [--host-write-hold-s S] "
                    "[--taxel-ohm OHM] [--mux-ron-ohm OHM] [--mux-c-pf PF] [--sh-c-pf PF] [--aa-c-nf NF] "
                    "[--hx711-sps 10|80] [--hx711-clock-error REL] [--drum-driver-microsteps N] [--no-index-sensor] "
                    "[--index-bounce N] [--eeprom-write OFFSET:HEX] [--actuator-stall-g G] [--state-addr ADDR] "
                    "FIRMWARE.elf\n");
    exit(2);
}

int main(int argc, char **argv)
{
    const char *board = NULL, *fw = NULL, *wave_path = NULL;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
#define NEXT() (i + 1 < argc ? argv[++i] : (usage(), ""))
        if (!strcmp(a, "--board")) board = NEXT();
        else if (!strcmp(a, "--no-pace")) opt_pace = 0;
        else if (!strcmp(a, "--reset-on-open")) opt_reset_on_open = 1;
        else if (!strcmp(a, "--bootloader")) opt_bootloader = NEXT();
        else if (!strcmp(a, "--boot-ms")) opt_boot_ms = atof(NEXT());
        else if (!strcmp(a, "--wave")) wave_path = NEXT();
        else if (!strcmp(a, "--spring-k")) opt_spring_k = opt_spring_k0 = atof(NEXT());
        else if (!strcmp(a, "--contact-mm")) opt_contact_mm = opt_contact_mm0 = atof(NEXT());
        else if (!strcmp(a, "--act-steps-per-mm")) opt_act_steps_per_mm = atof(NEXT());
        else if (!strcmp(a, "--rear-stop-mm")) opt_rear_stop_mm = atof(NEXT());
        else if (!strcmp(a, "--actuator-stall-g")) opt_stall_g = atof(NEXT());
        else if (!strcmp(a, "--counts-per-g")) opt_counts_per_g = atof(NEXT());
        else if (!strcmp(a, "--loadcell-offset")) opt_loadcell_offset = atol(NEXT());
        else if (!strcmp(a, "--tel-ms")) opt_tel_ms = atof(NEXT());
        else if (!strcmp(a, "--max-seconds")) opt_max_seconds = atof(NEXT());
        else if (!strcmp(a, "--clock-lock")) opt_clock_lock = NEXT();
        else if (!strcmp(a, "--host-write-hold-s")) opt_host_write_hold_s = atof(NEXT());
        else if (!strcmp(a, "--taxel-ohm")) opt_taxel_ohm = atof(NEXT());
        else if (!strcmp(a, "--mux-ron-ohm")) opt_mux_ron_ohm = atof(NEXT());
        else if (!strcmp(a, "--mux-c-pf")) opt_mux_c_pf = atof(NEXT());
        else if (!strcmp(a, "--sh-c-pf")) opt_sh_c_pf = atof(NEXT());
        else if (!strcmp(a, "--aa-c-nf")) atomic_store(&opt_aa_c_nf, atof(NEXT()));
        else if (!strcmp(a, "--hx711-sps")) opt_hx711_sps = atof(NEXT());
        else if (!strcmp(a, "--drum-driver-microsteps")) opt_driver_microsteps = atof(NEXT());
        else if (!strcmp(a, "--no-index-sensor")) opt_index_sensor = 0;
        else if (!strcmp(a, "--actuator-reversed")) atomic_store(&act_reversed_req, 1);
        else if (!strcmp(a, "--index-bounce")) opt_index_bounce = atoi(NEXT());
        else if (!strcmp(a, "--hx711-clock-error")) opt_hx711_clock_error = atof(NEXT());
        else if (!strcmp(a, "--eeprom-write")) opt_eeprom_write = NEXT();
        else if (!strcmp(a, "--state-addr")) opt_state_addr = (int)strtol(NEXT(), NULL, 0);
        else if (a[0] == '-') usage();
        else fw = a;
    }
    if (!board || !fw) usage();
    is_uno = !strcmp(board, "uno");
    if (!is_uno && strcmp(board, "mega")) usage();
    if (opt_hx711_sps != 10.0 && opt_hx711_sps != 80.0) usage();
    if (!(opt_driver_microsteps >= 1.0 && opt_driver_microsteps <= 256.0)) usage();
    if (!(opt_hx711_clock_error > -0.2 && opt_hx711_clock_error < 0.2)) usage();

    host_pid = getppid();
    if (host_pid == 1) return 1;
    setvbuf(stdout, NULL, _IOLBF, 0);

    elf_firmware_t f;
    memset(&f, 0, sizeof f);
    if (elf_read_firmware(fw, &f)) {
        fprintf(stderr, "cannot read %s\n", fw);
        return 1;
    }
    avr = avr_make_mcu_by_name(is_uno ? "atmega328p" : "atmega2560");
    if (!avr) {
        fprintf(stderr, "no simavr core\n");
        return 1;
    }
    avr_init(avr);
    avr->frequency = 16000000;
    avr->vcc = avr->avcc = avr->aref = 5000;
    avr_load_firmware(avr, &f);
    avr->frequency = 16000000;
    avr->log = LOG_ERROR;
    avr->sleep = sleep_paced_by_harness;
    if (opt_bootloader && boot_load(opt_bootloader)) {
        fprintf(stderr, "cannot load the bootloader %s\n", opt_bootloader);
        return 1;
    }

    int at_once = 0;
    if (wave_path && load_wave(wave_path, -1, &at_once)) { /* no scan yet: it plays from the first */
        fprintf(stderr, "cannot read waveform %s\n", wave_path);
        return 1;
    }
    if (opt_eeprom_write && eeprom_write_arg(opt_eeprom_write)) {
        fprintf(stderr, "bad --eeprom-write %s (OFFSET:HEXBYTES)\n", opt_eeprom_write);
        return 1;
    }
    extint_poll(); /* before the first instruction: a pin that goes low at init would otherwise arm the poll */
    if (is_uno) uno_setup();
    else mega_setup();

    if (bridge_open()) {
        fprintf(stderr, "cannot create the pty: %s\n", strerror(errno));
        return 1;
    }
    const char *pty = pty_name;
    int ino = -1;
    if (opt_reset_on_open) {
        ino = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
        if (ino < 0 || inotify_add_watch(ino, pty, IN_OPEN) < 0) {
            fprintf(stderr, "inotify on %s: %s\n", pty, strerror(errno));
            return 1;
        }
    }
    printf("PTY %s\n", pty);

    pthread_t th, watch;
    pthread_create(&th, NULL, stdin_thread, NULL);
    pthread_create(&watch, NULL, parent_watch_thread, NULL);

    if (opt_clock_lock) {
        clock_lock_open(opt_clock_lock, is_uno);
        lock_cycle = avr->cycle;
    }
    double wall0 = now_s();
    uint64_t cycle0 = avr->cycle;
    double hold_left = 0.0; /* in reset (bootloader wait) for this much more simulated time, s */
    uint64_t next_check = 0;
    double last_poll_wall = -1.0; /* wall time of the last poll() of the pty and the open detector */
    int mcu_reset_seen = 0;
    for (;;) {
        if (hold_left > 0.0) {
            /* the bootloader's wait passes as simulated time: at wall pace when paced (1 ms steps), at once when not,
             * and never past the host's grant */
            double step = 0.001;
            if (opt_pace) {
                struct timespec ts = {0, 1000000};
                double held = now_s();
                nanosleep(&ts, NULL);
                step = now_s() - held;
            }
            double room = host_grant_room_s();
            if (step > room) step = room > 0.0 ? room : 0.0;
            if (step > hold_left) step = hold_left;
            hold_left -= step;
            if (lock_slots) clock_lock_publish(step);
            if (step <= 0.0) host_grant_wait();
            if (hold_left <= 0.0) {
                hold_left = 0.0;
                avr_reset(avr);
                extint_poll();
                bridge_reset();
                if (is_uno) uno_after_reset();
                wall0 = now_s();
                cycle0 = avr->cycle;
            }
            if (atomic_load(&quit_requested)) break;
            continue;
        }
        /* the core runs to the next poll (at least one step), each board's per-step work in its own loop */
        int state;
        if (is_uno) {
            do {
                uint64_t cycle_before = avr->cycle;
                int busy_before = !avr->sreg[S_I] || probes_high;
                uint32_t pc_before = avr->pc;
                int ran = avr->state == cpu_Running;
                /* an instruction outside the candidate loop's span (an interrupt's, a callee's) ends the pass
                 * undecoded */
                int pure = ran && pc_before >= spin_head && pc_before - spin_head <= SPIN_MAX_BACK
                           && spin_pure(pc_before);
                state = core_step();
                busy_account(cycle_before, busy_before || !avr->sreg[S_I]);
                if (ran && state == cpu_Running) spin_step(pc_before, pure, next_check);
                if (state == cpu_Done || state == cpu_Crashed) break;
                if (avr->pc == avr->reset_pc) mcu_reset_seen = 1;
            } while (avr->cycle < next_check);
        } else {
            do {
                state = core_step();
                if (state == cpu_Done || state == cpu_Crashed) break;
                if (avr->pc == avr->reset_pc) mcu_reset_seen = 1; /* the MCU reset itself (watchdog): its reset vector */
            } while (avr->cycle < next_check);
        }
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "simavr core stopped (state %d)\n", state);
            break;
        }
        next_check = avr->cycle + POLL_CYCLES; /* every 0.1 ms of simulated time */
        poll_period_arm();
        extint_poll();
        /* a host's open first: its DTR resets the board before it can send (the bytes it writes at once, waiting
         * in the pty, then reach the bootloader, never the old sketch: both can land in one poll's gap) */
        /* one poll() for the pty and the open detector instead of a read() on each (both empty almost always):
         * both are seen at the same instant, so an open and the bytes written after it are found together, and the
         * open is handled first */
        /* paced, at most one every POLL_WALL_S of wall time: the paced core runs its 0.1 ms polls in bursts ~10x
         * faster than the wall clock between its sleeps, and the sleep itself (below) wakes on the same two fds */
        struct pollfd pfd[2] = {{.fd = pty_master, .events = POLLIN}, {.fd = ino, .events = POLLIN}};
        double wall_poll = opt_pace ? now_s() : 0.0;
        if (opt_pace && wall_poll - last_poll_wall < POLL_WALL_S) {
            pfd[0].revents = pfd[1].revents = 0;
        } else {
            if (poll(pfd, ino >= 0 ? 2 : 1, 0) <= 0) pfd[0].revents = pfd[1].revents = 0;
            last_poll_wall = wall_poll;
        }
        if (ino >= 0 && pfd[1].revents) {
            char buf[4096];
            ssize_t n = read(ino, buf, sizeof buf);
            if (n > 0 && boot_loaded) { /* a host opened the port: DTR reset into the bootloader */
                boot_dtr_reset(is_uno ? uno_after_reset : mega_after_reset);
                wall0 = now_s();
                cycle0 = avr->cycle;
                continue;
            }
            if (n > 0) { /* a host opened the port: DTR reset, bootloader wait */
                hold_left = opt_boot_ms * 1e-3;
                printf("RESET t=%.6f\n", sim_s());
                continue;
            }
        }
        bridge_poll(pfd[0].revents != 0);
        if (boot_loaded) boot_watch();
        if (is_uno) uno_poll();
        else mega_poll();
        if (atomic_load(&quit_requested)) break;
        if (atomic_exchange(&reset_requested, 0)) {
            avr_reset(avr);
            extint_poll();
            /* MCUSR: what reset the MCU (avr_reset cleared it) */
            int cause = atomic_load(&reset_cause_req);
            if (cause & 1) avr_regbit_set(avr, avr->reset_flags.porf);
            if (cause & 2) avr_regbit_set(avr, avr->reset_flags.extrf);
            if (cause & 4) avr_regbit_set(avr, avr->reset_flags.borf);
            if (cause & 1) /* a power cycle loses the SRAM (avr_reset keeps it, as a warm reset does) */
                memset(avr->data + avr->ioend + 1, 0, avr->ramend - avr->ioend);
            bridge_reset();
            if (is_uno) uno_after_reset();
            else {
                hx_power_cycle = cause & 1;
                mega_after_reset();
            }
            printf("RESET t=%.6f\n", sim_s());
        } else if (!is_uno && mcu_reset_seen) { /* the MCU reset itself (the watchdog): the pins need driving again */
            mcu_reset_seen = 0;
            bridge_reset();
            mega_after_reset();
            printf("RESET t=%.6f cause=mcu\n", sim_s());
        }
        if (opt_max_seconds > 0 && sim_s() >= opt_max_seconds) break;
        if (lock_slots) {
            clock_lock_publish(0.0);
            clock_lock_wait();
            double paused = host_grant_wait();
            paused += host_write_wait();
            if (paused > 0.0) { /* the world paused for the host: paced, it goes on from here, no burst */
                wall0 = now_s();
                cycle0 = avr->cycle;
            }
        }
        if (opt_pace) {
            double ahead = (double)(avr->cycle - cycle0) / avr->frequency - (now_s() - wall0);
            if (ahead > (is_uno ? PACE_AHEAD_UNO_S : PACE_AHEAD_MEGA_S)) {
                /* sleep until the wall clock has caught up, or until the host writes (when the bridge can take its
                 * bytes: a chunk still being fed to the UART would wake it at once) or opens the port */
                struct timespec ts = {0, (long)(ahead * 1e9)};
                struct pollfd wake[2] = {{.fd = rx_pos == rx_len ? pty_master : -1, .events = POLLIN},
                                         {.fd = ino, .events = POLLIN}};
                if (ppoll(wake, 2, &ts, NULL) > 0) last_poll_wall = -1.0; /* poll at the next 0.1 ms */
            } else if (ahead < -0.25) { /* fell far behind (slow host): do not try to catch up in a burst */
                wall0 = now_s();
                cycle0 = avr->cycle;
            }
        }
    }
    printf("EXIT t=%.6f lost_tx_bytes=%llu spin_skips=%llu\n", sim_s(), (unsigned long long)tx_lost,
           (unsigned long long)spin_skips);
    fflush(stdout);
    _exit(0); /* the stdin reader thread may still block in fgets */
}
