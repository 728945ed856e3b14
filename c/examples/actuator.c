/*
 * An actuator node: joins the bus, subscribes to robot/cmd and prints each command as
 * "robot/cmd HEX from 0xTT", COUNT times (0: for ever), then exits.
 *
 *   ups-actuator IFACE NODE_ID [COUNT]                e.g. ups-actuator vcan0 0xA1 3
 */
#include <stdio.h>
#include <stdlib.h>

#include "channels.h"
#include "socketcan.h"

static ups_node_t node;

int main(int argc, char **argv)
{
    if (argc < 3) {
        fprintf(stderr, "usage: %s IFACE NODE_ID [COUNT]\n", argv[0]);
        return 2;
    }
    unsigned long count = argc > 3 ? strtoul(argv[3], NULL, 0) : 0;
    int sock = socketcan_open(argv[1], 0);
    if (sock < 0) {
        perror(argv[1]);
        return 1;
    }
    ups_init(&node, strtoull(argv[2], NULL, 0), UPS_BUS_CLASSIC);
    ups_start(&node, socketcan_clock_ms()); /* its UPS_NOTE_FILTERS opens the socket */
    int cmd = ups_subscribe(&node, UPS_UID_ROBOT_CMD, socketcan_clock_ms());
    unsigned long got = 0;
    int ready = 0;
    while (count == 0 || got < count) {
        ups_frame_t frame;
        ups_event_t event;
        int delivered = socketcan_step(sock, &node, 1, &frame, &event);
        if (delivered < 0 || ups_join_state(&node) < 0 || ups_channel_state(&node, cmd) < 0) {
            fprintf(stderr, "ups-actuator: failed (join %d, channel %d)\n",
                    ups_join_state(&node), ups_channel_state(&node, cmd));
            return 1;
        }
        if (!ready && ups_channel_state(&node, cmd) == UPS_CHANNEL_BOUND) {
            ready = 1;
            fprintf(stderr, "ups-actuator: TxNode 0x%02x, robot/cmd at etag 0x%04x\n",
                    ups_txnode(&node), ups_channel_etag(&node, cmd));
        }
        if (delivered && event.channel == cmd) {
            printf("robot/cmd ");
            for (unsigned i = 0; i < event.size; ++i) {
                printf("%02x", event.data[i]);
            }
            printf(" from 0x%02x\n", event.txnode);
            fflush(stdout);
            ++got;
        }
    }
    return 0;
}
