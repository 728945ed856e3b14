/*
 * libups-ecb internals shared by its sources: the calls between them. Not part of the API.
 *
 * The sources stand in floors: ups_ecb.c on top (the dispatcher: receiving and its checks,
 * the life cycle, Hello and the recovery window, the timers' entry, the blob), the protocol's
 * seams under it, ups_ecb_join.c (TxNodes, the census, Offers, claims), ups_ecb_bind.c (etags,
 * who uses them, quotas, held requests, rosters, declarations; it asks ups_ecb_join.c who holds
 * a TxNode) and ups_ecb_elect.c (the election), then ups_ecb_rt.c (the admission analysis, a
 * pure function) and at the bottom ups_ecb_util.c (byte helpers, counters, the TX queue),
 * which calls none of them. No part calls the dispatcher: what it must do after a part's call
 * (a CLAIM from a TxNode nobody holds) the part returns. ups_ecb_join.c and ups_ecb_bind.c call
 * each other (the join tells the binding when a node entry changes hands; the binding asks the
 * join who holds a TxNode). Each section below says which source defines it.
 */
#ifndef UPS_ECB_INTERNAL_H
#define UPS_ECB_INTERNAL_H

#include "ups_ecb.h"
#include "ups_ecb_rt.h"

/* the identifier layout (docs/protocol.md, Identifier layout) */
#define UPS_ECB__PRIO_SHIFT 21u
#define UPS_ECB__TXNODE_SHIFT 14u
#define UPS_ECB__ETAG_MASK 0x3FFFu
#define UPS_ECB__MGMT 0x7Fu
#define UPS_ECB__FIRST_ETAG 0x0010u
#define UPS_ECB__LARGE_ETAG 0x3000u
#define UPS_ECB__NO_SLOT (-1)

static inline uint32_t ups_ecb__id(uint32_t priority, uint32_t txnode, uint32_t etag)
{
    return (priority << UPS_ECB__PRIO_SHIFT) | (txnode << UPS_ECB__TXNODE_SHIFT) | etag;
}

/** Milliseconds from @p then to @p now on the wrapping clock (valid up to 2^31 ms). */
static inline uint32_t ups_ecb__since(uint32_t now, uint32_t then)
{
    return now - then;
}

/* ---- ups_ecb_util.c: what every source stands on; it calls no other source ------------------ */

/** Count one in a saturating counter. */
void ups_ecb__count(UPS_ECB_COUNTER_T *counter);
/** Raise notes (UPS_ECB_NOTE_...). */
void ups_ecb__note(ups_ecb_t *ecb, unsigned bits);
/** Whether two 8-byte values are equal. */
int ups_ecb__same8(const uint8_t *a, const uint8_t *b);
/** Copy @p n bytes (or zero them when @p from is NULL) in a loop no compiler makes a call of;
 *  first byte first, so @p to may overlap @p from from below. */
void ups_ecb__copy(uint8_t *to, const uint8_t *from, unsigned n);
/** Read 8 bytes big-endian. */
uint64_t ups_ecb__get64(const uint8_t *in);
/** Queue a classic extended frame of @p len bytes: 0, or 8 of @p data. The CAN-ECB's frames
 *  have no other length, and all have TxNode 0x7F and priority 0 or 1 (ups_ecb_echo_t keys
 *  them so). It is sent in the order of the identifiers (FIFO among equals); a full queue
 *  drops it, counted (tx_dropped). */
void ups_ecb__send(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len);
/** Remove the first frame of the TX queue (it was sent). */
void ups_ecb__pop(ups_ecb_t *ecb);
/** Queue a CAN-ECB frame of TxNode 0x7F at priority 0 with the etag field @p field and the 8
 *  data bytes @p data as they go on the wire, or none when @p data is NULL. */
void ups_ecb__send8(ups_ecb_t *ecb, unsigned field, const uint8_t *data);
/** Whether TxNode @p txnode asked while unknown since the last Hello (a stray: ecb->strays, which
 *  the dispatcher keeps). */
static inline unsigned ups_ecb__stray(const ups_ecb_t *ecb, unsigned txnode)
{
    return ((unsigned)ecb->strays[(txnode & 0x7Fu) / 8u] >> (txnode % 8u)) & 1u;
}
/** Milliseconds from @p then to @p now on the low 16 bits of the clock (valid up to 65 s). */
static inline uint32_t ups_ecb__since16(uint32_t now, uint16_t then)
{
    return (uint16_t)((uint16_t)now - then);
}
/** The oldest age a timestamp keeps (2^30 ms, 12.4 days): ups_ecb__age() pulls an older one up
 *  to it, so that ages stay below 2^31 ms and a clock wrap never makes an old entry young. */
#define UPS_ECB__AGE_MAX 0x40000000u
/** The age of timestamp @p *then at @p now, at most UPS_ECB__AGE_MAX (@p *then is moved up to
 *  now - UPS_ECB__AGE_MAX when older). Called at least every 2^30 ms on every timestamp that
 *  lives longer (every tick does), it keeps each age exact up to that bound. */
uint32_t ups_ecb__age(uint32_t now, uint32_t *then);

/* ---- ups_ecb_join.c ---------------------------------------------------------------------- */

void ups_ecb__join_init(ups_ecb_t *ecb);
/** The CAN-ECB starts (ecb->now): the leases count from now. */
void ups_ecb__join_started(ups_ecb_t *ecb);
/** A frame of TxNode @p txnode: its lease starts again. */
void ups_ecb__join_seen(ups_ecb_t *ecb, unsigned txnode);
/** The node entry (index into ecb->join.nodes) that holds @p txnode, or UPS_ECB__NO_SLOT. */
int ups_ecb__holder(const ups_ecb_t *ecb, unsigned txnode);
/** A frame of TxNode 0x7F at priority 0 in the join's part of the table (Knock, Stage, Query,
 *  Offer, Assign, Census; op/arg as the etag field says), or CLAIM from @p txnode. Returns 1
 *  for a CLAIM that is a request from a TxNode nobody holds (the dispatcher counts it and may
 *  say Hello), else 0. */
int ups_ecb__join_rx(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len);
void ups_ecb__join_tick(ups_ecb_t *ecb);
/** A frame of the join's (Assign, TxNodesFull, Failed) that this CAN-ECB did not send, heard
 *  while serving: its correction where it contradicts the table (counted in conflicts). */
void ups_ecb__join_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data);
/** Stop the census (standing by); Offers lapse as usual. */
void ups_ecb__join_stop(ups_ecb_t *ecb);
/** Whether a census runs (the election will not stand by while it does). */
int ups_ecb__join_busy(const ups_ecb_t *ecb);
/** The recovery window ended: answer a Knock that came during it. */
void ups_ecb__join_recovered(ups_ecb_t *ecb);
/** The blob's TxNode section: written size (0 when @p cap is short), and taken back (0, or
 *  UPS_ERR_ARGUMENT for a section that does not fit or contradicts itself). */
size_t ups_ecb__join_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap);
int ups_ecb__join_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size);

/* ---- ups_ecb_bind.c ---------------------------------------------------------------------- */

/** Empty the durable tables (channels, streams); the rest stays as ups_ecb_init zeroed it. */
void ups_ecb__bind_init(ups_ecb_t *ecb);
/** A node's request or report from the TxNode of node entry @p slot (PUB_BIND, SUB_BIND,
 *  UNSUB, DECLARE, Roster, PUB_BIND(c), SUB_AT, PUB_AT), well-formed as the dispatcher's
 *  checks let through (kind_of); held in a recovery window as the protocol says. */
void ups_ecb__bind_request(ups_ecb_t *ecb, int slot, uint32_t id, const uint8_t *data);
/** An event frame on @p etag (the channel is in use: its lease starts again). */
void ups_ecb__bind_event(ups_ecb_t *ecb, unsigned etag);
/** Node entry @p slot was given to another node id or reclaimed: forget what its TxNode used
 *  and declared, and the bindings it created count against nobody. Call it (and the next)
 *  while the entry still has its old TxNode. */
void ups_ecb__bind_forget(ups_ecb_t *ecb, int slot);
/** Node entry @p slot was assigned again to the node id it held (a join again): forget what
 *  its TxNode used and declared; the bindings it created still count against it. */
void ups_ecb__bind_rejoined(ups_ecb_t *ecb, int slot);
/** A CAN-ECB frame this one did not send (Bind, EtagsFull, Limit, Grant, Refuse, Failed,
 *  Uses, RosterEnd), well-formed (kind_of), heard while serving: correct what contradicts the
 *  tables. */
void ups_ecb__bind_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len);
/** The recovery window ended: answer the held requests and the rosters asked meanwhile. */
void ups_ecb__bind_recovered(ups_ecb_t *ecb);
/** Standing by: drop the answers in progress (rosters). */
void ups_ecb__bind_stop(ups_ecb_t *ecb);
void ups_ecb__bind_tick(ups_ecb_t *ecb);
/** The blob's binding section: written size (0 when @p cap is short), and taken back into the
 *  empty tables (after ups_ecb__bind_init; 0, or UPS_ERR_ARGUMENT for a section that does not
 *  fit or contradicts itself, the tables then partly filled: the caller empties them). */
size_t ups_ecb__bind_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap);
int ups_ecb__bind_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size);

/* ---- ups_ecb_elect.c --------------------------------------------------------------------- */

#define UPS_ECB__SAY_HELLO 0x01u /* the election's verdict: say Hello and open a recovery window */

/** Start as a candidate (the caller says Hello). */
void ups_ecb__elect_start(ups_ecb_t *ecb);
/** Hello, Serving or Probe (@p status: its etag-field bits 8-11) of @p instance from another
 *  CAN-ECB, or any other CAN-ECB frame (@p status of that frame, @p instance NULL); @p busy
 *  while this one holds what standing by would drop (a recovery, a census). Returns
 *  UPS_ECB__SAY_HELLO or 0. */
unsigned ups_ecb__elect_heard(ups_ecb_t *ecb, unsigned status, const uint8_t *instance,
                              uint32_t id, const uint8_t *data, int busy);
/** Standing by: a frame that asks the serving CAN-ECB for an answer (Knock, SUB_BIND,
 *  PUB_BIND, PUB_BIND(c)), watched. Returns UPS_ECB__SAY_HELLO or 0. */
unsigned ups_ecb__elect_asked(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len);
unsigned ups_ecb__elect_tick(ups_ecb_t *ecb);
/** Milliseconds from ecb->now until the election's next timer (0: due now; 0xFFFFFFFF: none
 *  runs): a tick then is the next that can change anything of the election's. */
uint32_t ups_ecb__elect_next(const ups_ecb_t *ecb);

#endif /* UPS_ECB_INTERNAL_H */
