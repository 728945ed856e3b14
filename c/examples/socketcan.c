/* A minimal Linux SocketCAN port of libups (see socketcan.h). */
#include "socketcan.h"

#include <errno.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define MAX_FILTERS 64

int socketcan_open(const char *name, int fd)
{
    int sock = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    struct sockaddr_can addr;
    if (sock < 0) {
        return -1;
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = (int)if_nametoindex(name);
    /* no filter: the socket receives nothing until socketcan_filters(), as a CAN controller
     * after reset (bxCAN with no filter bank active): the first UPS_NOTE_FILTERS opens it */
    if (addr.can_ifindex == 0 || setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, NULL, 0) < 0 ||
        (fd && setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &fd, sizeof fd) < 0) ||
        bind(sock, (struct sockaddr *)&addr, sizeof addr) < 0) {
        close(sock);
        return -1;
    }
    return sock;
}

int socketcan_filters(int sock, const ups_filter_t *filters, int count)
{
    struct can_filter kernel[MAX_FILTERS];
    int n = count <= MAX_FILTERS ? count : 1;
    for (int i = 0; i < n; ++i) {
        /* extended data frames only: the EFF and RTR flags take part in the match */
        kernel[i].can_id = (count <= MAX_FILTERS ? filters[i].id : 0u) | CAN_EFF_FLAG;
        kernel[i].can_mask = (count <= MAX_FILTERS ? filters[i].mask : 0u) | CAN_EFF_FLAG |
                             CAN_RTR_FLAG;
    }
    return setsockopt(sock, SOL_CAN_RAW, CAN_RAW_FILTER, kernel,
                      (socklen_t)((size_t)n * sizeof kernel[0]));
}

int socketcan_send(int sock, const ups_frame_t *frame)
{
    struct canfd_frame out;
    size_t size = (frame->flags & UPS_FRAME_FD) ? CANFD_MTU : CAN_MTU;
    memset(&out, 0, sizeof out);
    out.can_id = frame->id | CAN_EFF_FLAG;
    out.len = frame->len;
    out.flags = (frame->flags & UPS_FRAME_BRS) ? CANFD_BRS : 0;
    memcpy(out.data, frame->data, frame->len);
    if (write(sock, &out, size) == (ssize_t)size) {
        return 0;
    }
    return errno == ENOBUFS || errno == EAGAIN ? 1 : -1;
}

int socketcan_recv(int sock, ups_frame_t *frame, int timeout_ms)
{
    struct pollfd pfd = {sock, POLLIN, 0};
    struct canfd_frame in;
    int ready = poll(&pfd, 1, timeout_ms);
    if (ready <= 0) {
        return ready;
    }
    ssize_t got = read(sock, &in, sizeof in);
    if (got != CAN_MTU && got != CANFD_MTU) {
        return -1;
    }
    if (in.len > UPS_MTU) {
        return 0; /* an FD frame a build without UPS_WITH_FD has no room for: dropped, not cut */
    }
    frame->id = in.can_id & (in.can_id & CAN_EFF_FLAG ? CAN_EFF_MASK : CAN_SFF_MASK);
    frame->flags = (uint8_t)(((in.can_id & CAN_EFF_FLAG) ? UPS_FRAME_EXT : 0u) |
                             ((in.can_id & CAN_RTR_FLAG) ? UPS_FRAME_RTR : 0u) |
                             ((in.can_id & CAN_ERR_FLAG) ? UPS_FRAME_ERR : 0u) |
                             (got == CANFD_MTU ? UPS_FRAME_FD : 0u));
    frame->len = in.len;
    memcpy(frame->data, in.data, frame->len);
    return 1;
}

uint32_t socketcan_clock_ms(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (uint32_t)now.tv_sec * 1000u + (uint32_t)(now.tv_nsec / 1000000);
}

int socketcan_step(int sock, ups_node_t *node, int wait_ms, ups_frame_t *frame,
                   ups_event_t *event)
{
    int got = socketcan_recv(sock, frame, wait_ms);
    int delivered = 0;
    uint32_t now = socketcan_clock_ms();
    if (got < 0) {
        return -1;
    }
    if (got > 0) {
        delivered = ups_rx(node, now, frame, event);
    }
    ups_tick(node, now);
    if (ups_notes(node) & UPS_NOTE_FILTERS) {
        ups_filter_t filters[UPS_CHANNELS + 1];
        int n = ups_filters(node, filters, UPS_CHANNELS + 1);
        if (socketcan_filters(sock, filters, n) < 0) {
            return -1;
        }
    }
    const ups_frame_t *out;
    while ((out = ups_tx_peek(node)) != NULL && socketcan_send(sock, out) == 0) {
        ups_tx_pop(node);
    }
    return delivered;
}
