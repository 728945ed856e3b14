/*
 * A sensor node: joins the bus, publishes a 2-byte big-endian reading on robot/speed every
 * PERIOD_MS milliseconds, COUNT times (0: for ever), and exits.
 *
 *   ups-sensor IFACE NODE_ID [COUNT [PERIOD_MS]]      e.g. ups-sensor vcan0 0xA2 5 100
 */
#include <stdio.h>
#include <stdlib.h>

#include "channels.h"
#include "socketcan.h"

static ups_node_t node; /* the library's whole state: static storage, no heap */

int main(int argc, char **argv)
{
    if (argc < 3) {
        fprintf(stderr, "usage: %s IFACE NODE_ID [COUNT [PERIOD_MS]]\n", argv[0]);
        return 2;
    }
    unsigned long count = argc > 3 ? strtoul(argv[3], NULL, 0) : 0;
    uint32_t period = argc > 4 ? (uint32_t)strtoul(argv[4], NULL, 0) : 100u;
    int sock = socketcan_open(argv[1], 0);
    if (sock < 0) {
        perror(argv[1]);
        return 1;
    }
    ups_init(&node, strtoull(argv[2], NULL, 0), UPS_BUS_CLASSIC);
    ups_start(&node, socketcan_clock_ms()); /* its UPS_NOTE_FILTERS opens the socket */
    int speed = ups_advertise(&node, UPS_UID_ROBOT_SPEED, 2, socketcan_clock_ms());
    uint32_t next = 0;
    unsigned long sent = 0;
    int joined = 0;
    while (count == 0 || sent < count) {
        ups_frame_t frame;
        ups_event_t event;
        if (socketcan_step(sock, &node, 1, &frame, &event) < 0) {
            perror("socketcan");
            return 1;
        }
        if (ups_join_state(&node) < 0 || ups_channel_state(&node, speed) < 0) {
            fprintf(stderr, "ups-sensor: failed (join %d, channel %d)\n", ups_join_state(&node),
                    ups_channel_state(&node, speed));
            return 1;
        }
        if (!joined && ups_txnode(&node) >= 0) {
            joined = 1;
            fprintf(stderr, "ups-sensor: joined as TxNode 0x%02x\n", ups_txnode(&node));
        }
        uint32_t now = socketcan_clock_ms();
        if (ups_channel_state(&node, speed) == UPS_CHANNEL_BOUND && (int32_t)(now - next) >= 0) {
            uint8_t reading[2] = {(uint8_t)(sent >> 8), (uint8_t)sent};
            if (ups_publish(&node, speed, reading, 2) == UPS_OK) {
                ++sent;
                next = now + period;
            }
        }
    }
    for (int i = 0; i < 50; ++i) { /* the last event out */
        ups_frame_t frame;
        ups_event_t event;
        socketcan_step(sock, &node, 1, &frame, &event);
    }
    return 0;
}
