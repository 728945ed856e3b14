/*
 * libups internals: what every source stands on, defined in ups_util.c and here. The
 * identifier layout, the frames' codes, the flags, small inline helpers, and ups_util.c's calls
 * (size classes, byte helpers, counters, the TX queue). Not part of the API.
 *
 * The sources stand in floors, and each includes the headers of the floors under it: ups.c
 * (the dispatcher: receiving, the timers, the API's small calls) calls the protocol's seams,
 * ups_join.c (ups_join.h), ups_bind.c (ups_bind.h; ups_join.c calls it too) and ups_transfer.c
 * (ups_transfer.h; ups_bind.c calls it to give up a contradicted etag's transfers); all of them
 * stand on ups_util.c and this header, which include and call none of them.
 */
#ifndef UPS_UTIL_H
#define UPS_UTIL_H

#include "ups.h"

#define UPS__PRIO_SHIFT 21u
#define UPS__TXNODE_SHIFT 14u
#define UPS__ETAG_MASK 0x3FFFu
#define UPS__MGMT 0x7Fu
#define UPS__FIRST_ETAG 0x0010u
#define UPS__LARGE_ETAG 0x3000u
#define UPS__DEFAULT_PRIORITY 0x80u
#define UPS__FIRST_EVENT_ID (2u << UPS__PRIO_SHIFT) /* lower identifiers are management */
/* events may fill the TX queue but for its last place, which stays for management frames: a
 * node that publishes as fast as its queue drains still asks, claims and answers Hello */
#define UPS__EVENT_ROOM (UPS_TX_DEPTH - 1u)
#define UPS__NO_ETAG 0xFFFFu /* beyond UPS__ETAG_MASK: no frame's etag field */

/* management frames (docs/protocol.md, "Management frames"): the two high bits of the etag
 * field of TxNode 0x7F at priority 0 (op), and in status frames its bits 8-11 (status) */
#define OP_STAGE 0u
#define OP_QUERY 1u
#define OP_ASSIGN 2u
#define OP_STATUS 3u
#define ST_CENSUS 0u
#define ST_TXNODES_FULL 1u
#define ST_ETAGS_FULL 2u
#define ST_HELLO 3u
#define ST_GRANT 4u
#define ST_REFUSE 5u
#define ST_SERVING 6u
#define ST_FAILED 7u
#define ST_LIMIT 8u
#define ST_PROBE 9u
#define ST_USES_SUB 10u   /* the roster a gateway asks for: nodes ignore it */
#define ST_USES_PUB 11u
#define ST_ROSTER_END 12u
#define ST_KNOCK 15u
#define OFFER_BIT 0x80u
/* node requests (the etag field, priority 0, the node's TxNode) */
#define RQ_PUB_BIND 1u
#define RQ_SUB_BIND 2u
#define RQ_UNSUB 3u
#define RQ_CLAIM 4u
#define RQ_DECLARE 5u
#define RQ_ROSTER 6u /* a gateway's: nodes ignore it */
#define RQ_PUB_BIND_CLASS 8u

/* channel flags */
#define UPS__SUB 0x01u    /* the application receives it */
#define UPS__PUB 0x02u    /* the application publishes on it */
#define UPS__BOUND 0x04u  /* etag is relied on */
#define UPS__PEND 0x08u   /* a request is outstanding (or due once joined) */
#define UPS__ASKED 0x10u  /* ... and has been sent: Binds from now on may answer it */
#define UPS__REBIND 0x20u /* bound again after a contradiction: answers settle first */
#define UPS__CAND 0x40u   /* etag is a candidate answer, settling */
#define UPS__WAIT 0x80u   /* a publisher's pause before its first event on a larger class */

/* node mode bits */
#define UPS__FD 0x01u
#define UPS__OWE_CLAIM 0x02u    /* a CLAIM is owed: to an Offer, or in the answer to Hello */
#define UPS__ANNOUNCE_DUE 0x04u /* a Hello came within a second of the last answer */
#define UPS__RECENT 0x08u       /* the last answer to Hello started less than a second ago */
#define UPS__REFUSED 0x10u      /* joining: a TxNodesFull or Failed of its id is open ... */
#define UPS__REFUSED_FAILED 0x20u /* ... and the latest was Failed (else TxNodesFull) */

/* the frames a channel owes the CAN-ECB (ups_channel_t.owe), queued one at a time, lowest bit
 * first, when there is room and no management frame waits before them (ups__queue_owed) */
#define UPS__OWE_REQUEST 0x01u /* SUB_BIND, PUB_BIND or PUB_BIND(c) */
#define UPS__OWE_SUB_AT 0x02u  /* = UPS__SUB << 1 */
#define UPS__OWE_PUB_AT 0x04u  /* = UPS__PUB << 1; >> 2: its priority (1) */
#define UPS__OWE_DECLARE 0x08u
#define UPS__OWE_UNSUB 0x10u

static inline uint32_t ups__make_id(uint32_t priority, uint32_t txnode, uint32_t etag)
{
    return (priority << UPS__PRIO_SHIFT) | (txnode << UPS__TXNODE_SHIFT) | etag;
}

/** Milliseconds from @p then (the low 16 bits of the clock, as the node keeps its times) to
 *  @p now (the clock): the difference of the low 16 bits, right across any wrap, up to 65 s. */
static inline uint16_t ups__since(uint32_t now, uint16_t then)
{
    return (uint16_t)(now - then);
}

static inline uint16_t get16(const uint8_t *in)
{
    return (uint16_t)(((unsigned)in[0] << 8) | in[1]);
}

/** A time as the node keeps it: the low 16 bits of the millisecond clock. */
static inline uint16_t now16(uint32_t now_ms)
{
    return (uint16_t)now_ms;
}

static inline int joined(const ups_node_t *node)
{
    return node->join == UPS_JOIN_JOINED;
}

static inline void note(ups_node_t *node, unsigned bits)
{
    node->notes = (uint8_t)(node->notes | bits);
}

static inline int ups__valid_channel(const ups_node_t *node, int channel)
{
    return channel >= 0 && channel < UPS_CHANNELS && node->channels[channel].flags != 0u;
}

/* ups_util.c: it calls no other source */
/** The size class of an etag: 0 for one-frame events, 1..4 for transfers. */
unsigned ups__class(unsigned etag);
/** The largest event of a size class. */
uint32_t ups__class_max(unsigned cls);
/** Copy @p n bytes (the buffers do not overlap), or zero them when @p from is NULL, in a loop
 *  that no compiler makes a call of memcpy or memset of. */
void ups__copy(uint8_t *to, const uint8_t *from, unsigned n);
/** Count one in a saturating counter. */
void ups__count(UPS_COUNTER_T *counter);
/** Whether two 8-byte values (node ids, UIDs) are equal. */
int ups__same8(const uint8_t *a, const uint8_t *b);
/** Nibble @p stage of a 64-bit big-endian id, most significant first. */
unsigned ups__nibble(const uint8_t *id, unsigned stage);
/** Write @p value big-endian into @p out[0..7]. */
void ups__put64(uint8_t *out, uint64_t value);
/** Queue a frame (sorted by identifier, FIFO among equals). 0, or UPS_ERR_FULL (counted). */
int ups__push(ups_node_t *node, uint32_t id, uint8_t flags, const uint8_t *data, unsigned len);
/** Queue a frame of 8 bytes from this node's TxNode: a request, SUB_AT (priority 0) or PUB_AT
 *  (priority 1). */
void ups__push_request(ups_node_t *node, unsigned priority, unsigned etag, const uint8_t *data);
/** Take the first @p first frames out of the TX queue, and every frame on @p etag
 *  (UPS__NO_ETAG: none): ups_tx_pop() takes the frame sent; a node that stops relying on an
 *  etag drops what is queued on it (by the time it would go, the etag may be another
 *  channel's); the transfers on it are the caller's to give up (ups__transfer_drop). */
void ups__tx_drop(ups_node_t *node, unsigned first, unsigned etag);

#endif /* UPS_UTIL_H */
