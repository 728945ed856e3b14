/*
 * libups internals: the calls of ups_join.c (the join, moves, the answer to Hello), for ups.c.
 * Not part of the API.
 */
#ifndef UPS_JOIN_H
#define UPS_JOIN_H

#include "ups_util.h"

/** A well-formed frame of TxNode 0x7F at priority 0 (etag field: @p op, @p arg), heard while
 *  joining or joined: the join, moves, Hello, refusals and verdicts. */
void ups__config_frame(ups_node_t *node, unsigned op, unsigned arg, const uint8_t *data,
                       uint32_t now);
/** Queue the join's frames that wait for room (the CLAIM of an Offer, Stage answers). */
void ups__join_refill(ups_node_t *node);
void ups__tick_join(ups_node_t *node, uint32_t now);
void ups__tick_hello(ups_node_t *node, uint32_t now);

#endif /* UPS_JOIN_H */
