/*
 * One MCU, node and broker: an autopilot-like board that carries the bus's CAN-ECB
 * (libups-ecb) and is a node of that bus itself (libups), in one image, on one CAN port. No
 * computer is needed on the bus: the board gives the other nodes their TxNodes and binds their
 * channels, and its own node joins through it like any other.
 *
 * Its node publishes board/uptime (4 bytes, big-endian milliseconds) every PERIOD_MS and
 * prints each robot/speed event (as ups-sensor publishes them) as "robot/speed HEX from 0xTT".
 * The CAN-ECB's durable state (its blob) lives in STATE_FILE, standing for a flash page:
 * taken back at start, written whenever the library says it changed, before anything queued
 * since goes on the bus. SIGINT or SIGTERM ends it with a line of what it did.
 *
 *   ups-broker IFACE NODE_ID STATE_FILE [PERIOD_MS]    e.g. ups-broker vcan0 0xB0 ecb.blob 500
 *
 * Two things differ from a node alone (c/README.md, "Porting the CAN-ECB"):
 *   - the one socket accepts every extended frame: the CAN-ECB hears the whole bus, so the
 *     node's acceptance filters are not programmed (the node filters in software);
 *   - the node and the CAN-ECB share the port, and a CAN controller (a SocketCAN socket too,
 *     unless CAN_RAW_RECV_OWN_MSGS is set) does not receive the frames it sent itself: each
 *     frame one of them sends is given to the other, as the bus would carry it to a second
 *     controller. Without this the node never hears its Assign and the CAN-ECB never hears
 *     the node's requests.
 */
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "channels.h"
#include "socketcan.h"
#include "ups_ecb.h"

#define UPS_UID_BOARD_UPTIME 0x3c6ff8d4d5054897ULL /* board/uptime (ups uid board/uptime) */

static ups_ecb_t ecb;   /* the CAN-ECB's whole state: static storage, no heap */
static ups_node_t node; /* the board's own node */
static uint8_t blob[UPS_ECB_BLOB_MAX]; /* a flash page's worth */
static unsigned long blob_writes;
static volatile sig_atomic_t stop;

static void on_signal(int sig)
{
    (void)sig;
    stop = 1;
}

/* A random instance: what names this run of the CAN-ECB in the election (a board draws it
 * from its hardware random source). */
static uint64_t random_instance(void)
{
    uint64_t value = 0;
    int fd = open("/dev/urandom", O_RDONLY);
    if (fd < 0 || read(fd, &value, sizeof value) != (ssize_t)sizeof value) {
        value = (uint64_t)getpid() << 32 ^ socketcan_clock_ms(); /* not for a product */
    }
    if (fd >= 0) {
        close(fd);
    }
    return value;
}

/* Take the blob back from the "flash" (the file), if there is one. */
static void restore(const char *path)
{
    FILE *f = fopen(path, "rb");
    if (f == NULL) {
        fprintf(stderr, "ups-broker: no state in %s: a new bus\n", path);
        return;
    }
    size_t size = fread(blob, 1, sizeof blob, f);
    fclose(f);
    if (ups_ecb_restore(&ecb, blob, size) == UPS_OK) {
        fprintf(stderr, "ups-broker: state taken back from %s (%zu B)\n", path, size);
    } else {
        fprintf(stderr, "ups-broker: state in %s refused: the CAN-ECB relearns the bus\n", path);
    }
}

/* Write the blob: a new file renamed over the old one, so that a reset in the middle leaves
 * the old state (on flash: two pages written in turn, the newer valid one taken at start). */
static int save(const char *path)
{
    char tmp[4096];
    size_t size = ups_ecb_save(&ecb, blob, sizeof blob);
    if (size == 0 || (size_t)snprintf(tmp, sizeof tmp, "%s.new", path) >= sizeof tmp) {
        return -1;
    }
    int fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd < 0) {
        return -1;
    }
    int ok = write(fd, blob, size) == (ssize_t)size && fsync(fd) == 0;
    if (close(fd) != 0 || !ok || rename(tmp, path) != 0) {
        return -1;
    }
    ++blob_writes;
    return 0;
}

/* After every call on the CAN-ECB: its notes. The state first, before anything is sent. */
static int ecb_notes(const char *path)
{
    unsigned notes = ups_ecb_notes(&ecb);
    if ((notes & UPS_ECB_NOTE_STATE) && save(path) < 0) {
        fprintf(stderr, "ups-broker: cannot write %s: %s\n", path, strerror(errno));
        return -1;
    }
    if (notes & UPS_ECB_NOTE_ROLE) {
        static const char *const roles[] = {"stopped", "candidate", "serving", "standing by"};
        fprintf(stderr, "ups-broker: CAN-ECB %s\n", roles[ups_ecb_role(&ecb) & 3]);
    }
    return 0;
}

/* A frame for the node, from the bus or from the CAN-ECB beside it. */
static void node_rx(uint32_t now, const ups_frame_t *frame, int speed)
{
    ups_event_t event;
    if (ups_rx(&node, now, frame, &event) && event.channel == speed) {
        printf("robot/speed ");
        for (unsigned i = 0; i < event.size; ++i) {
            printf("%02x", event.data[i]);
        }
        printf(" from 0x%02x\n", event.txnode);
        fflush(stdout);
    }
    (void)ups_notes(&node); /* UPS_NOTE_FILTERS: the socket accepts every frame already */
}

/* Send both queues, lowest identifier first, as arbitration would order them; each frame
 * sent is given to the other party. 0, or -1 on error. */
static int send_all(int sock, uint32_t now, int speed, const char *path)
{
    for (;;) {
        const ups_frame_t *from_ecb = ups_ecb_tx_peek(&ecb);
        const ups_frame_t *from_node = ups_tx_peek(&node);
        int ecb_first = from_ecb != NULL && (from_node == NULL || from_ecb->id <= from_node->id);
        const ups_frame_t *out = ecb_first ? from_ecb : from_node;
        if (out == NULL) {
            return 0;
        }
        int sent = socketcan_send(sock, out);
        if (sent != 0) {
            return sent < 0 ? -1 : 0; /* busy: the rest on the next pass */
        }
        ups_frame_t copy = *out;
        if (ecb_first) {
            ups_ecb_tx_pop(&ecb);
            node_rx(now, &copy, speed);
        } else {
            ups_tx_pop(&node);
            ups_ecb_rx(&ecb, now, &copy);
            if (ecb_notes(path) < 0) {
                return -1;
            }
        }
    }
}

int main(int argc, char **argv)
{
    if (argc < 4) {
        fprintf(stderr, "usage: %s IFACE NODE_ID STATE_FILE [PERIOD_MS]\n", argv[0]);
        return 2;
    }
    const char *path = argv[3];
    uint32_t period = argc > 4 ? (uint32_t)strtoul(argv[4], NULL, 0) : 1000u;
    int sock = socketcan_open(argv[1], 0);
    ups_filter_t every = {0u, 0u}; /* mask 0: every extended frame, for the CAN-ECB */
    if (sock < 0 || socketcan_filters(sock, &every, 1) < 0) {
        perror(argv[1]);
        return 1;
    }
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);

    uint32_t now = socketcan_clock_ms();
    ups_ecb_init(&ecb, NULL, random_instance());
    restore(path);
    ups_ecb_start(&ecb, now); /* Hello, then the recovery window */
    uint64_t node_id = strtoull(argv[2], NULL, 0);
    ups_init(&node, node_id, UPS_BUS_CLASSIC);
    ups_start(&node, now); /* Knock: joins through the CAN-ECB beside it */
    int uptime = ups_advertise(&node, UPS_UID_BOARD_UPTIME, 4, now);
    int speed = ups_subscribe(&node, UPS_UID_ROBOT_SPEED, now);
    (void)ups_notes(&node);
    uint32_t start = now, next = now;
    int joined = 0, bound = 0;
    unsigned long published = 0;
    if (ecb_notes(path) < 0) {
        return 1;
    }
    while (!stop) {
        ups_frame_t frame;
        int got = socketcan_recv(sock, &frame, 1);
        now = socketcan_clock_ms();
        if (got < 0 && errno != EINTR) {
            perror("socketcan");
            return 1;
        }
        if (got > 0) { /* every frame of the bus to both */
            ups_ecb_rx(&ecb, now, &frame);
            if (ecb_notes(path) < 0) {
                return 1;
            }
            node_rx(now, &frame, speed);
        }
        ups_ecb_tick(&ecb, now);
        if (ecb_notes(path) < 0) {
            return 1;
        }
        ups_tick(&node, now);
        (void)ups_notes(&node);
        if (!joined && ups_txnode(&node) >= 0) {
            joined = 1;
            fprintf(stderr, "ups-broker: node 0x%llx joined as TxNode 0x%02x\n",
                    (unsigned long long)node_id, ups_txnode(&node));
        }
        if (!bound && ups_channel_state(&node, uptime) == UPS_CHANNEL_BOUND &&
            ups_channel_state(&node, speed) == UPS_CHANNEL_BOUND) {
            bound = 1;
            fprintf(stderr, "ups-broker: board/uptime at etag 0x%04x, robot/speed at etag 0x%04x\n",
                    ups_channel_etag(&node, uptime), ups_channel_etag(&node, speed));
        }
        if (ups_join_state(&node) < 0 || ups_channel_state(&node, uptime) < 0 ||
            ups_channel_state(&node, speed) < 0) { /* refused or timed out: ask again */
            fprintf(stderr, "ups-broker: node: join %d, board/uptime %d, robot/speed %d\n",
                    ups_join_state(&node), ups_channel_state(&node, uptime),
                    ups_channel_state(&node, speed));
            if (ups_join_state(&node) < 0) {
                ups_start(&node, now);
            }
            if (ups_channel_state(&node, uptime) < 0) {
                uptime = ups_advertise(&node, UPS_UID_BOARD_UPTIME, 4, now);
            }
            if (ups_channel_state(&node, speed) < 0) {
                speed = ups_subscribe(&node, UPS_UID_ROBOT_SPEED, now);
            }
        }
        if (ups_channel_state(&node, uptime) == UPS_CHANNEL_BOUND && (int32_t)(now - next) >= 0) {
            uint32_t ms = now - start;
            uint8_t data[4] = {(uint8_t)(ms >> 24), (uint8_t)(ms >> 16), (uint8_t)(ms >> 8),
                               (uint8_t)ms};
            if (ups_publish(&node, uptime, data, 4) == UPS_OK) {
                ++published;
                next = now + period;
            }
        }
        if (send_all(sock, now, speed, path) < 0) {
            perror("socketcan");
            return 1;
        }
    }
    const ups_ecb_counters_t *c = ups_ecb_counters(&ecb);
    fprintf(stderr,
            "ups-broker: stopped: CAN-ECB %s, %lu joined, %lu bound, %lu state writes; "
            "node published %lu\n",
            ups_ecb_role(&ecb) == UPS_ECB_SERVING ? "serving" : "not serving",
            (unsigned long)c->joined, (unsigned long)c->bound, blob_writes, published);
    close(sock);
    return 0;
}
