/*
 * libups: the dispatcher (see ups.h): receiving (every frame is classified here, checked
 * against the tables of docs/protocol.md and handed to the join, the binding or the transfers),
 * the timers' entry point, sending from the TX queue, events, and the API's small calls.
 *
 * It stands on the protocol's seams, which it calls: the join and the answer to Hello in
 * ups_join.c; binding, the contradiction rule and real-time declarations in ups_bind.c; events
 * larger than one frame in ups_transfer.c. They and this file stand on ups_util.c (size
 * classes, byte helpers, counters, the TX queue), which calls none of them.
 */
#include "ups_bind.h"
#include "ups_join.h"
#include "ups_transfer.h"
#include "ups_util.h"

/* ---- the TX queue's refill ----------------------------------------------------------------- */

/** Queue what waits for room in the TX queue: the join's frames, a transfer's next frames. */
static void refill(ups_node_t *node)
{
    if (node->join == UPS_JOIN_JOINING) {
        ups__join_refill(node);
    }
#if UPS_WITH_TRANSFERS
    ups__transfer_refill(node);
#endif
}

/* ---- receiving ----------------------------------------------------------------------------- */

/** The index of the received channel bound to @p etag, or UPS_CHANNELS. */
static unsigned rx_channel(const ups_node_t *node, uint16_t etag)
{
    unsigned i = 0;
    for (; i < UPS_CHANNELS; ++i) {
        const ups_channel_t *ch = &node->channels[i];
        if ((ch->flags & (UPS__SUB | UPS__BOUND)) == (UPS__SUB | UPS__BOUND) && ch->etag == etag) {
            break;
        }
    }
    return i;
}

/** Whether @p etag (big-endian) is one the CAN-ECB binds, and @p txnode one it gives out. */
static int stream_ok(const uint8_t *etag, unsigned txnode)
{
    return (unsigned)(get16(etag) - UPS__FIRST_ETAG) <= UPS__ETAG_MASK - UPS__FIRST_ETAG &&
           txnode < UPS__MGMT;
}

/** Whether another node's frame (a request, SUB_AT or PUB_AT) matches a row of the tables. */
static int node_frame_ok(unsigned priority, unsigned etag, const uint8_t *data, unsigned len)
{
    if (len != 8u) {
        return 0;
    }
    if (etag >= UPS__FIRST_ETAG) {
        return 1; /* SUB_AT (priority 0) or PUB_AT (1) */
    }
    if (priority != 0u || !((0x1E7Eu >> etag) & 1u)) { /* PUB_BIND ... ROSTER, PUB_BIND(1-4) */
        return 0;
    }
    /* DECLARE: etag:u16 size:u8 period:u16 deadline:u16 jitter:u8; sizes in bytes (0-8) on
     * etags of one frame, in frames (1-255) from 0x3000; period and deadline at least 1 */
    return etag != RQ_DECLARE ||
           (stream_ok(data, 0u) &&
            (get16(data) < UPS__LARGE_ETAG ? data[2] <= 8u : data[2] != 0u) &&
            (data[3] | data[4]) != 0u && (data[5] | data[6]) != 0u);
}

/* For each status frame (bits 8-11 of the etag field): 0x80 if it carries 8 data bytes, and
 * its largest low byte plus one (0: no such frame): Census carries its epoch there, Limit and
 * Uses a TxNode, RosterEnd a TxNode (its top bit: done, checked apart), the others nothing. */
static const uint8_t status_rule[16] = {16u,    0x81u, 0x81u, 0x81u, 0x81u, 0x81u, 0x81u, 0x81u,
                                        0xFFu, 0x81u, 0xFFu, 0xFFu, 0xFFu, 0u,    0u,    1u};

/** Whether a frame of TxNode 0x7F at priority 0 (etag field: @p op, @p arg) matches a row of
 *  the tables, with the data length and field ranges they give. */
static int config_ok(unsigned op, unsigned arg, const uint8_t *data, unsigned len)
{
    unsigned status = arg >> 8;
    if (op == OP_STATUS) {
        unsigned rule = status_rule[status];
        unsigned low = status == ST_ROSTER_END ? arg & 0x7Fu : arg & 0xFFu; /* bit 7: done */
        if (low >= (rule & 0x7Fu) || len != ((rule >> 4) & 8u)) {
            return 0;
        }
        if (status == ST_ROSTER_END && (arg & 0x80u)) { /* done: no next UID */
            return (data[0] | data[1] | data[2] | data[3] | data[4] | data[5] | data[6] |
                    data[7]) == 0u;
        }
        if (status != ST_GRANT && status != ST_REFUSE) {
            return 1;
        }
        if (!stream_ok(data, data[2])) {
            return 0;
        }
        if (status == ST_REFUSE) {
            return stream_ok(data + 4, data[3]); /* the stream that would miss */
        }
        return (unsigned)(data[3] - 2u) < 0x7Eu && /* a priority of 0x02-0x7F, then zeros */
               (data[4] | data[5] | data[6] | data[7]) == 0u;
    }
    if (len != (op == OP_STAGE ? 0u : 8u)) {
        return 0;
    }
    if (op != OP_QUERY) {
        return op == OP_STAGE || (arg & ~OFFER_BIT) < UPS__MGMT; /* Offer, Assign: a TxNode */
    }
    /* Query: 1-15 nibbles of prefix, the last one repeated in the identifier, zeros after */
    unsigned last = (arg >> 4) & 0xFu;
    for (unsigned s = last; s < 16u; ++s) {
        if (ups__nibble(data, s) != (s == last ? (arg & 0xFu) : 0u)) {
            return 0;
        }
    }
    return last != 15u;
}

static int on_event(ups_node_t *node, const ups_frame_t *frame, uint32_t now, ups_event_t *event)
{
    uint16_t etag = (uint16_t)(frame->id & UPS__ETAG_MASK);
    uint8_t txnode = (uint8_t)((frame->id >> UPS__TXNODE_SHIFT) & UPS__MGMT);
    if (joined(node) && txnode == node->txnode) {
        ups__count(&node->counters.own_echo);
        return 0;
    }
    unsigned i = rx_channel(node, etag);
    if (i >= UPS_CHANNELS) {
        ups__count(ups__etag_known(node, etag) ? &node->counters.filtered
                                               : &node->counters.unknown);
        return 0;
    }
    event->channel = (uint8_t)i;
    event->priority = (uint8_t)(frame->id >> UPS__PRIO_SHIFT);
    event->txnode = txnode;
    if (etag >= UPS__LARGE_ETAG) {
#if UPS_WITH_TRANSFERS
        return ups__transfer_rx(node, now, frame, txnode, etag, event);
#else
        (void)now;
        return 0; /* never bound: rx_channel() found nothing */
#endif
    }
    if (frame->len > 8u) {
        ups__count(&node->counters.malformed);
        return 0;
    }
    event->data = frame->data;
    event->size = frame->len;
    return 1;
}

int ups_rx(ups_node_t *node, uint32_t now_ms, const ups_frame_t *frame, ups_event_t *event)
{
    uint32_t now = now_ms;
    uint32_t id = frame->id;
    unsigned len = frame->len;
    const uint8_t *data = frame->data;
    unsigned priority = id >> UPS__PRIO_SHIFT;
    unsigned txnode = (id >> UPS__TXNODE_SHIFT) & UPS__MGMT;
    unsigned etag = id & UPS__ETAG_MASK;
    UPS_COUNTER_T *counter = &node->counters.malformed;
    int got = 0;
    if ((frame->flags & (UPS_FRAME_EXT | UPS_FRAME_RTR | UPS_FRAME_ERR)) != UPS_FRAME_EXT ||
        id > 0x1FFFFFFFu || len > UPS_MTU) {
        counter = &node->counters.foreign;
    } else if (priority >= 2u && txnode != UPS__MGMT && etag >= UPS__FIRST_ETAG) {
        counter = NULL;
        got = on_event(node, frame, now, event);
    } else if (frame->flags & UPS_FRAME_FD) {
        counter = &node->counters.foreign; /* management frames are classic frames */
    } else if (txnode != UPS__MGMT) { /* another node's frames need no action */
        if (node_frame_ok(priority, etag, data, len)) {
            counter = joined(node) && txnode == node->txnode ? &node->counters.own_echo : NULL;
        }
    } else if (priority == 1u) {
        if (etag >= UPS__FIRST_ETAG && len == 8u) {
            counter = NULL;
            ups__on_bind(node, (uint16_t)etag, data, now);
        }
    } else if (priority == 0u && config_ok(etag >> 12, etag & 0xFFFu, data, len)) {
        counter = NULL;
        if (node->join == UPS_JOIN_JOINING || joined(node)) {
            ups__config_frame(node, etag >> 12, etag & 0xFFFu, data, now);
        }
    }
    if (counter != NULL) {
        ups__count(counter);
    }
    refill(node);
    return got;
}

/* ---- the timers ---------------------------------------------------------------------------- */

void ups_tick(ups_node_t *node, uint32_t now_ms)
{
    uint32_t now = now_ms;
    if (node->join == UPS_JOIN_JOINING) {
        ups__tick_join(node, now);
    } else if (joined(node)) {
        ups__tick_bind(node, now);
        ups__tick_hello(node, now);
    }
#if UPS_WITH_TRANSFERS
    ups__transfer_tick(node, now);
#endif
    refill(node);
}

/* ---- the API's small calls ----------------------------------------------------------------- */

int ups_init(ups_node_t *node, uint64_t node_id, unsigned bus_mode)
{
    ups__copy((uint8_t *)node, NULL, (unsigned)sizeof *node);
    if (bus_mode > UPS_BUS_FD || (bus_mode == UPS_BUS_FD && !UPS_WITH_FD)) {
        return UPS_ERR_ARGUMENT;
    }
    ups__put64(node->node_id, node_id);
    node->txnode = UPS__MGMT;
    node->mode = bus_mode == UPS_BUS_FD ? UPS__FD : 0u;
    node->burst[0][1] = node->burst[1][1] = 16u;
#if UPS_DECLARATIONS
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
        node->decl[i].channel = 0xFFu;
    }
#endif
    return UPS_OK;
}

const ups_frame_t *ups_tx_peek(const ups_node_t *node)
{
    return node->tx_count > 0u ? &node->tx[0] : NULL;
}

void ups_tx_pop(ups_node_t *node)
{
    if (node->tx_count == 0u) {
        return;
    }
    const ups_frame_t *sent = &node->tx[0];
    if ((sent->id >> UPS__TXNODE_SHIFT) == node->txnode && joined(node)) { /* priority 0 */
        ups__sent_request(node, sent->id & UPS__ETAG_MASK, sent->data);
    }
    ups__tx_drop(node, 1u, UPS__NO_ETAG);
    refill(node);
}

unsigned ups_notes(ups_node_t *node)
{
    unsigned notes = node->notes;
    node->notes = 0u;
    return notes;
}

int ups_idle(const ups_node_t *node)
{
    unsigned busy = node->tx_count | (node->mode & (UPS__OWE_CLAIM | UPS__ANNOUNCE_DUE |
                                                     UPS__RECENT));
    busy |= node->join == UPS_JOIN_JOINING;
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) { /* waiting, settling, pausing, owing */
        busy |= node->channels[i].owe |
                (node->channels[i].flags & (UPS__PEND | UPS__CAND | UPS__WAIT));
    }
#if UPS_DECLARATIONS
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) { /* its retry or verdict wait runs */
        const ups_declaration_t *decl = &node->decl[i];
        if (decl->channel < UPS_CHANNELS && decl->state == UPS_DECL_WAITING) {
            busy |= node->channels[decl->channel].flags & UPS__BOUND;
        }
    }
#endif
#if UPS_WITH_TRANSFERS
    busy |= node->tx_left;
    for (unsigned i = 0; i < UPS_RX_TRANSFERS; ++i) {
        busy |= node->rx[i].etag;
    }
#endif
    return busy == 0u;
}

int ups_join_state(const ups_node_t *node)
{
    return node->join;
}

int ups_txnode(const ups_node_t *node)
{
    return joined(node) ? (int)node->txnode : -1;
}

int ups_publish(ups_node_t *node, int channel, const uint8_t *data, uint16_t size)
{
    if (!ups__valid_channel(node, channel) || (data == NULL && size > 0u)) {
        return UPS_ERR_ARGUMENT;
    }
    ups_channel_t *ch = &node->channels[channel];
    if (!(ch->flags & UPS__PUB)) {
        return UPS_ERR_ARGUMENT;
    }
    if (!(ch->flags & UPS__BOUND) || (ch->flags & UPS__WAIT) || !joined(node)) {
        if (ch->flags & UPS__REBIND) {
            ups__count(&node->counters.unbound_dropped);
        }
        return UPS_ERR_UNBOUND;
    }
    uint32_t id = ups__make_id(ch->priority, node->txnode, ch->etag); /* 0x02 or more */
#if UPS_WITH_TRANSFERS
    if (ch->etag >= UPS__LARGE_ETAG) {
        return ups__transfer_tx(node, channel, id, data, size);
    }
#endif
    if (size > 8u || ch->etag >= UPS__LARGE_ETAG) {
        return UPS_ERR_TOO_LARGE; /* (moved to a larger class: no transfers in this build) */
    }
    uint8_t flags = (UPS_WITH_FD && (node->mode & UPS__FD)) ? UPS_FRAME_FD | UPS_FRAME_BRS : 0u;
    return ups__push(node, id, flags, data, size);
}

int ups_filters(const ups_node_t *node, ups_filter_t *out, int max)
{
    int n = 0;
    if (n < max) {
        out[n].id = UPS__MGMT << UPS__TXNODE_SHIFT;
        out[n].mask = UPS__MGMT << UPS__TXNODE_SHIFT;
    }
    ++n;
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        const ups_channel_t *ch = &node->channels[i];
        if ((ch->flags & (UPS__SUB | UPS__BOUND)) == (UPS__SUB | UPS__BOUND)) {
            if (n < max) {
                out[n].id = ch->etag;
                out[n].mask = UPS__ETAG_MASK;
            }
            ++n;
        }
    }
    return n;
}

const ups_counters_t *ups_counters(const ups_node_t *node)
{
    return &node->counters;
}
