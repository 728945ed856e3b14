/*
 * A minimal Linux SocketCAN port of libups for the examples: a raw CAN socket, libups frames in
 * and out, kernel acceptance filters, and a millisecond clock. See c/README.md for other ports.
 */
#ifndef UPS_SOCKETCAN_H
#define UPS_SOCKETCAN_H

#include "ups.h"

/** Open a raw CAN socket on interface @p name (CAN FD frames too when @p fd). It receives nothing
 *  until socketcan_filters() (as a controller after reset): socketcan_step() programs the
 *  filters on UPS_NOTE_FILTERS, the first time after ups_start(). -1 on error. */
int socketcan_open(const char *name, int fd);

/** Program the kernel's acceptance filters from libups' list (accept every extended frame when
 *  it is longer than the kernel takes). 0, or -1 on error. */
int socketcan_filters(int sock, const ups_filter_t *filters, int count);

/** Send one frame. 0, 1 when the interface is busy (try again later), -1 on error. */
int socketcan_send(int sock, const ups_frame_t *frame);

/** Receive one frame, waiting at most @p timeout_ms. 1: a frame, 0: none (or one longer than
 *  UPS_MTU, dropped), -1: error. */
int socketcan_recv(int sock, ups_frame_t *frame, int timeout_ms);

/** Milliseconds of a monotonic clock (wrapping). */
uint32_t socketcan_clock_ms(void);

/** Run @p node for one pass: receive into @p frame for up to @p wait_ms, tick, program the
 *  filters on UPS_NOTE_FILTERS (before the next frame is received), send. Returns 1 and fills
 *  @p event when an event came (its data may point into @p frame: keep both until the next
 *  pass), 0 otherwise, -1 on error. */
int socketcan_step(int sock, ups_node_t *node, int wait_ms, ups_frame_t *frame,
                   ups_event_t *event);

#endif
