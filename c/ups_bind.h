/*
 * libups internals: the calls of ups_bind.c (binding, the contradiction rule, declarations), for
 * ups.c and ups_join.c. Not part of the API.
 */
#ifndef UPS_BIND_H
#define UPS_BIND_H

#include "ups_util.h"

/** The request @p kind for @p uid went out: if its channel asks just that, Binds from now on
 *  may answer it (a Bind received before the request went does not count). */
void ups__sent_request(ups_node_t *node, unsigned kind, const uint8_t *uid);
/** EtagsFull, Failed or Limit (UPS_ERR_ code @p why) for @p uid, or a Bind of a size class
 *  the node cannot receive (UPS_ERR_TOO_LARGE): the request of its channel, if one was sent and
 *  waits (not a re-binding's), ends with it once it stood 3 s with no Bind answering the
 *  request while the node kept asking. */
void ups__refused(ups_node_t *node, const uint8_t *uid, int why, uint32_t now);
/** Queue the next frame a channel owes, if any; 1 when it queued one. */
int ups__queue_owed(ups_node_t *node, uint32_t now);
/** Bind(etag, uid) from the CAN-ECB or anyone: the contradiction rule, then answers. */
void ups__on_bind(ups_node_t *node, uint16_t etag, const uint8_t *uid, uint32_t now);
/** Whether @p etag was ever heard bound (to a channel of this node, or, with UPS_HEARD_BINDS,
 *  to any): an event on it that the node does not receive is filtered, not unknown. */
int ups__etag_known(const ups_node_t *node, uint16_t etag);
/** The request and declaration retries, settling, the publisher's pause. */
void ups__tick_bind(ups_node_t *node, uint32_t now);
#if UPS_DECLARATIONS
/** Grant (of @p priority) or Refuse for this node's TxNode and @p etag: taken only for a
 *  stream it declared; the latest one is the answer once it stood 0.5 s. */
void ups__on_verdict(ups_node_t *node, uint16_t etag, int granted, uint8_t priority,
                     uint32_t now);
#endif

#endif /* UPS_BIND_H */
