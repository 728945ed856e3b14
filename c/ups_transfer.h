/*
 * libups internals: the calls of ups_transfer.c (events larger than one frame), for ups.c and
 * ups_bind.c; only in the builds with transfers (UPS_WITH_TRANSFERS). Not part of the API.
 */
#ifndef UPS_TRANSFER_H
#define UPS_TRANSFER_H

#include "ups_util.h"

#if UPS_WITH_TRANSFERS
int ups__transfer_rx(ups_node_t *node, uint32_t now, const ups_frame_t *frame, uint8_t txnode,
                     uint16_t etag, ups_event_t *event);
/** ups_publish() of an event on a large etag (@p id): UPS_ERR_TOO_LARGE beyond its size class
 *  or UPS_MAX_EVENT, UPS_ERR_BUSY while another transfer is sent, else as ups__push(). */
int ups__transfer_tx(ups_node_t *node, int channel, uint32_t id, const uint8_t *data,
                     uint16_t size);
void ups__transfer_refill(ups_node_t *node);
void ups__transfer_tick(ups_node_t *node, uint32_t now);
/** The node stops relying on @p etag: the rest of a transfer being sent on it is not sent, and
 *  transfers being received on it are given up. */
void ups__transfer_drop(ups_node_t *node, uint16_t etag);
#endif

#endif /* UPS_TRANSFER_H */
