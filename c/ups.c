/*
 * libups: the node's frame handling (see ups.h): the TX queue, receiving (every frame is
 * classified here, checked against the tables of docs/protocol.md and handed to the join, the
 * binding or the transfers), the timers' entry point, events, and the API's small calls.
 *
 * The join and the answer to Hello are in ups_join.c; binding, the contradiction rule and
 * real-time declarations in ups_bind.c; events larger than one frame in ups_transfer.c.
 */
#include "ups_internal.h"

void ups__put64(uint8_t *out, uint64_t value)
{
    for (unsigned i = 8u; i-- > 0u;) {
        out[i] = (uint8_t)value;
        value >>= 8;
    }
}

/* ---- the TX queue -------------------------------------------------------------------------- */

/** tx[to] = tx[from], field by field (a struct copy of 68 bytes would call memcpy). */
static void move_frame(ups_node_t *node, unsigned to, unsigned from)
{
    node->tx[to].id = node->tx[from].id;
    node->tx[to].flags = node->tx[from].flags;
    node->tx[to].len = node->tx[from].len;
    for (unsigned i = 0; i < UPS_MTU; ++i) {
        node->tx[to].data[i] = node->tx[from].data[i];
    }
}

int ups__push(ups_node_t *node, uint32_t id, uint8_t flags, const uint8_t *data, unsigned len)
{
    if (node->tx_count >= (id >= UPS__FIRST_EVENT_ID ? UPS__EVENT_ROOM : UPS_TX_DEPTH) ||
        len > UPS_MTU) {
        ups__count(&node->counters.tx_dropped);
        return UPS_ERR_FULL;
    }
    unsigned at = node->tx_count;
    while (at > 0u && node->tx[at - 1u].id > id) {
        move_frame(node, at, at - 1u);
        --at;
    }
    node->tx[at].id = id; /* indexed, not through a pointer: -fsanitize=bounds checks it */
    node->tx[at].flags = (uint8_t)(flags | UPS_FRAME_EXT);
    node->tx[at].len = (uint8_t)len;
    for (unsigned i = 0; i < UPS_MTU; ++i) {
        node->tx[at].data[i] = i < len ? data[i] : 0u;
    }
    node->tx_count = (uint8_t)(node->tx_count + 1u);
    return UPS_OK;
}

/** A node frame from this node's TxNode: a request, SUB_AT or PUB_AT, with 8 bytes. */
void ups__push_request(ups_node_t *node, unsigned priority, unsigned etag, const uint8_t *data)
{
    (void)ups__push(node, ups__make_id(priority, node->txnode, etag), 0u, data, 8u);
}

/** The node stops relying on @p etag: what is queued on it does not go out (by the time it
 *  would, the etag may be another channel's), nor does the rest of a transfer on it, and no
 *  transfer begun on it is finished (contradiction rule 1). */
void ups__drop_etag(ups_node_t *node, uint16_t etag)
{
    unsigned kept = 0u;
    for (unsigned i = 0; i < node->tx_count; ++i) {
        if ((node->tx[i].id & UPS__ETAG_MASK) != etag) { /* requests: etags below 0x10 */
            move_frame(node, kept++, i);
        }
    }
    node->tx_count = (uint8_t)kept;
#if UPS_WITH_TRANSFERS
    ups__transfer_drop(node, etag);
#endif
}

static void refill(ups_node_t *node)
{
    if (node->join == UPS__WAITING) {
        ups__join_refill(node);
    }
#if UPS_WITH_TRANSFERS
    ups__transfer_refill(node);
#endif
}

/* ---- receiving ----------------------------------------------------------------------------- */

int ups__rx_channel(const ups_node_t *node, uint16_t etag)
{
    for (int i = 0; i < UPS_CHANNELS; ++i) {
        const ups_channel_t *ch = &node->channels[i];
        if ((ch->flags & (UPS__SUB | UPS__BOUND)) == (UPS__SUB | UPS__BOUND) && ch->etag == etag) {
            return i;
        }
    }
    return -1;
}

static int etag_ok(uint16_t etag)
{
    return etag >= UPS__FIRST_ETAG && etag <= UPS__ETAG_MASK;
}

static int stream_ok(uint16_t etag, unsigned txnode)
{
    return etag_ok(etag) && txnode < UPS__MGMT;
}

/** Whether a node frame (another node's request, SUB_AT or PUB_AT) is well formed. */
static int node_frame_ok(unsigned priority, uint16_t etag, const uint8_t *data, unsigned len)
{
    if (len != 8u) {
        return 0;
    }
    if (etag >= UPS__FIRST_ETAG) {
        return 1; /* SUB_AT or PUB_AT */
    }
    if (priority != 0u) {
        return 0;
    }
    if (etag == RQ_DECLARE) {
        uint16_t decl_etag = get16(data);
        unsigned largest = decl_etag < UPS__LARGE_ETAG ? 8u : 255u;
        return etag_ok(decl_etag) && data[2] <= largest &&
               (data[2] != 0u || decl_etag < UPS__LARGE_ETAG) && get16(data + 3) != 0u &&
               get16(data + 5) != 0u;
    }
    return (etag >= RQ_PUB_BIND && etag <= RQ_CLAIM) ||
           (etag > RQ_PUB_BIND_CLASS && etag <= RQ_PUB_BIND_CLASS + 4u);
}

/** A status frame (op 3) of the CAN-ECB; returns 0 when it is malformed. */
static int on_status(ups_node_t *node, unsigned arg, const uint8_t *data, unsigned len,
                     uint16_t now)
{
    unsigned status = arg >> 8;
    unsigned low = arg & 0xFFu;
    if (status == ST_CENSUS && low < 16u) {
        return len == 0u;
    }
    if (status == ST_LIMIT && low < UPS__MGMT) {
        if (len != 8u) {
            return 0;
        }
        if (joined(node) && low == node->txnode) {
            ups__refused(node, data, UPS_ERR_LIMIT);
        }
        return 1;
    }
    if (low != 0u || status == ST_CENSUS || status == ST_LIMIT || status > ST_PROBE) {
        return status == ST_KNOCK && low == 0u && len == 0u;
    }
    if (len != 8u) {
        return 0;
    }
    if (status == ST_GRANT || status == ST_REFUSE) {
        uint16_t etag = get16(data);
        if (!stream_ok(etag, data[2]) ||
            (status == ST_GRANT && (data[4] | data[5] | data[6] | data[7]) != 0u) ||
            (status == ST_REFUSE && !stream_ok(get16(data + 4), data[3]))) {
            return 0;
        }
#if UPS_DECLARATIONS
        if (joined(node) && data[2] == node->txnode) {
            ups__on_verdict(node, etag, status == ST_GRANT, data[3]);
        }
#endif
        return 1;
    }
    if (!joined(node)) {
        return 1; /* Hello, TxNodesFull, Failed while joining: ups__join_frame() */
    }
    if (status == ST_HELLO) {
        ups__on_hello(node, now);
    } else if (status == ST_ETAGS_FULL || status == ST_FAILED) {
        ups__refused(node, data, status == ST_FAILED ? UPS_ERR_FAILED : UPS_ERR_ETAGS_FULL);
    }
    return 1;
}

/** A frame of the CAN-ECB or of a joiner (TxNode 0x7F); returns 0 when it is malformed. */
static int on_config(ups_node_t *node, unsigned priority, uint16_t etag, const uint8_t *data,
                     unsigned len, uint16_t now)
{
    if (priority == 1u) {
        if (etag < UPS__FIRST_ETAG || len != 8u) {
            return 0;
        }
        ups__on_bind(node, etag, data, now);
        return 1;
    }
    if (priority != 0u) {
        return 0;
    }
    unsigned op = (unsigned)etag >> 12;
    unsigned arg = (unsigned)etag & 0xFFFu;
    if (op == OP_STAGE) {
        return len == 0u; /* another joiner's answer: nothing to do */
    }
    if (op == OP_STATUS) {
        if (!on_status(node, arg, data, len, now)) {
            return 0;
        }
    } else if (len != 8u) {
        return 0;
    } else if (op == OP_QUERY) {
        unsigned last = (arg >> 4) & 0xFu;
        if (last == 15u || nibble(data, last) != (arg & 0xFu)) {
            return 0;
        }
        for (unsigned s = last + 1u; s < 16u; ++s) {
            if (nibble(data, s) != 0u) {
                return 0;
            }
        }
    } else if ((arg & ~OFFER_BIT) >= UPS__MGMT) {
        return 0; /* Offer or Assign of TxNode 0x7F or beyond */
    } else if (joined(node) && !(arg & OFFER_BIT) && ups__same8(data, node->node_id) &&
               arg != node->txnode) {
        ups__move_to(node, arg, now);
    }
    if (node->join == UPS__WAITING) {
        ups__join_frame(node, op, arg, data, now);
    }
    return 1;
}

static int on_event(ups_node_t *node, const ups_frame_t *frame, uint16_t now, ups_event_t *event)
{
    uint16_t etag = (uint16_t)(frame->id & UPS__ETAG_MASK);
    uint8_t txnode = (uint8_t)((frame->id >> UPS__TXNODE_SHIFT) & UPS__MGMT);
    if (joined(node) && txnode == node->txnode) {
        ups__count(&node->counters.own_echo);
        return 0;
    }
    int i = ups__rx_channel(node, etag);
    if (i < 0) {
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
        return 0; /* never bound: ups__rx_channel() found nothing */
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
    uint16_t now = now16(now_ms);
    int got = 0;
    if (!(frame->flags & UPS_FRAME_EXT) || (frame->flags & (UPS_FRAME_RTR | UPS_FRAME_ERR)) ||
        frame->id > 0x1FFFFFFFu || frame->len > UPS_MTU) {
        ups__count(&node->counters.foreign);
        return 0;
    }
    unsigned priority = frame->id >> UPS__PRIO_SHIFT;
    unsigned txnode = (frame->id >> UPS__TXNODE_SHIFT) & UPS__MGMT;
    uint16_t etag = (uint16_t)(frame->id & UPS__ETAG_MASK);
    if (priority >= 2u && txnode != UPS__MGMT && etag >= UPS__FIRST_ETAG) {
        got = on_event(node, frame, now, event);
    } else if (frame->flags & UPS_FRAME_FD) {
        ups__count(&node->counters.foreign); /* management frames are classic frames */
    } else if (txnode != UPS__MGMT) {
        if (!node_frame_ok(priority, etag, frame->data, frame->len)) {
            ups__count(&node->counters.malformed);
        } else if (joined(node) && txnode == node->txnode) {
            ups__count(&node->counters.own_echo);
        } /* other nodes' requests need no action */
    } else if (!on_config(node, priority, etag, frame->data, frame->len, now)) {
        ups__count(&node->counters.malformed);
    }
    refill(node);
    return got;
}

/* ---- the timers ---------------------------------------------------------------------------- */

void ups_tick(ups_node_t *node, uint32_t now_ms)
{
    uint16_t now = now16(now_ms);
    if (node->join == UPS__WAITING) {
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
    uint8_t *raw = (uint8_t *)node;
    for (size_t i = 0; i < sizeof *node; ++i) {
        raw[i] = 0u;
    }
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
    node->tx_count = (uint8_t)(node->tx_count - 1u);
    for (unsigned i = 0; i < node->tx_count; ++i) {
        move_frame(node, i, i + 1u);
    }
    refill(node);
}

unsigned ups_notes(ups_node_t *node)
{
    unsigned notes = node->notes;
    node->notes = 0u;
    return notes;
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
    uint8_t priority = ch->priority < 2u ? 2u : ch->priority;
    uint32_t id = ups__make_id(priority, node->txnode, ch->etag);
    if (size > ups__class_max(ups__class(ch->etag)) || size > UPS_MAX_EVENT) {
        return UPS_ERR_TOO_LARGE;
    }
    if (ch->etag >= UPS__LARGE_ETAG) {
#if UPS_WITH_TRANSFERS
        return ups__transfer_tx(node, channel, id, data, size);
#else
        return UPS_ERR_TOO_LARGE; /* the channel moved to a larger class: no transfers here */
#endif
    }
    uint8_t flags = (node->mode & UPS__FD) ? (uint8_t)(UPS_FRAME_FD | UPS_FRAME_BRS) : 0u;
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
