/*
 * libups: the node (see ups.h). Sections: the TX queue; joining; binding; Hello answers;
 * declarations; receiving; the timers; the API's small calls.
 * Transfers (events larger than one frame) are in ups_transfer.c.
 */
#include "ups_internal.h"

/* management frames (docs/protocol.md, "Management frames") */
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
#define ST_KNOCK 15u
#define OFFER_BIT 0x80u
/* node requests (etag field) */
#define RQ_PUB_BIND 1u
#define RQ_SUB_BIND 2u
#define RQ_UNSUB 3u
#define RQ_CLAIM 4u
#define RQ_DECLARE 5u
#define RQ_PUB_BIND_CLASS 8u

/* timers, in milliseconds (docs/protocol.md, "Timers") */
#define KNOCK_FIRST 300u
#define KNOCK_MAX 2000u
#define RETRY_FIRST 50u
#define RETRY_MAX 1000u
#define RETRY_STEPS 8u /* 50+100+200+400+800+1000*4 = 5550 ms: the 9th wait gives up (5 s) */
#define SETTLE 50u
#define GROW_PAUSE 150u
#define HELLO_GAP 1000u
#define ANNOUNCE_PACE 1u

/* ---- helpers ------------------------------------------------------------------------------- */

static void put64(uint8_t *out, uint64_t value)
{
    for (unsigned i = 8u; i-- > 0u;) {
        out[i] = (uint8_t)value;
        value >>= 8;
    }
}

static inline uint16_t get16(const uint8_t *in)
{
    return (uint16_t)(((unsigned)in[0] << 8) | in[1]);
}

static inline uint16_t now16(uint32_t now_ms)
{
    return (uint16_t)now_ms;
}

static inline int joined(const ups_node_t *node)
{
    return node->join == UPS__READY;
}

static inline unsigned nibble(const uint8_t *id, unsigned stage)
{
    unsigned byte = id[stage >> 1];
    return (stage & 1u) ? (byte & 0xFu) : (byte >> 4);
}

static inline unsigned retry_delay(unsigned step)
{
    unsigned delay = RETRY_FIRST << (step < 5u ? step : 5u);
    return delay < RETRY_MAX ? delay : RETRY_MAX;
}

static inline void note(ups_node_t *node, unsigned bits)
{
    node->notes = (uint8_t)(node->notes | bits);
}

/** The entry of @p uid: one in use, or one that still owes the UID's UNSUB. */
static int find_uid(const ups_node_t *node, const uint8_t *uid)
{
    for (int i = 0; i < UPS_CHANNELS; ++i) {
        const ups_channel_t *ch = &node->channels[i];
        if ((ch->flags | ch->owe) != 0u && ups__same8(ch->uid, uid)) {
            return i;
        }
    }
    return -1;
}

static inline int valid_channel(const ups_node_t *node, int channel)
{
    return channel >= 0 && channel < UPS_CHANNELS && node->channels[channel].flags != 0u;
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

static void push_config(ups_node_t *node, uint32_t arg, const uint8_t *data, unsigned len)
{
    (void)ups__push(node, ups__make_id(0u, UPS__MGMT, arg), 0u, data, len);
}

/** A node frame from this node's TxNode: a request, SUB_AT or PUB_AT, with 8 bytes. */
static void push_request(ups_node_t *node, unsigned priority, unsigned etag, const uint8_t *data)
{
    (void)ups__push(node, ups__make_id(priority, node->txnode, etag), 0u, data, 8u);
}

/** Queue Stage answers while there is room (a Census asks for 16 frames at once). */
static void refill_stages(ups_node_t *node)
{
    for (unsigned b = 0; b < 2u; ++b) {
        uint8_t *burst = node->burst[b];
        while (burst[1] < 16u && node->tx_count < UPS_TX_DEPTH) {
            unsigned stage = burst[1];
            unsigned arg = ((unsigned)burst[0] << 8) | (stage << 4) | nibble(node->node_id, stage);
            push_config(node, arg, NULL, 0u); /* Stage: op 0 */
            burst[1] = (uint8_t)(stage + 1u);
        }
    }
}

static void refill(ups_node_t *node)
{
    if (node->join == UPS__WAITING) {
        if ((node->mode & UPS__OWE_CLAIM) && node->tx_count < UPS_TX_DEPTH) {
            node->mode = (uint8_t)(node->mode & ~UPS__OWE_CLAIM); /* before the Stage answers */
            push_request(node, 0u, RQ_CLAIM, node->node_id); /* from the offered TxNode */
        }
        refill_stages(node);
    }
#if UPS_WITH_TRANSFERS
    ups__transfer_refill(node);
#endif
}

/* ---- joining ------------------------------------------------------------------------------- */

static void knock(ups_node_t *node, uint16_t now)
{
    node->t_quiet = now;
    push_config(node, (OP_STATUS << 12) | (ST_KNOCK << 8), NULL, 0u);
}

/** A Census, Query or Offer: the CAN-ECB is at work, no Knock needed for a while. */
static void heard(ups_node_t *node, uint16_t now)
{
    node->t_quiet = now;
    node->knock_step = 0u;
}

static void answer_query(ups_node_t *node, unsigned epoch, unsigned from)
{
    unsigned slot = 0u;
    if (node->burst[0][1] < 16u && node->burst[0][0] != epoch) {
        slot = 1u;
        if (node->burst[1][1] < 16u && node->burst[1][0] != epoch) {
            ups__count(&node->counters.tx_dropped); /* a third query at once: replace one */
        }
    }
    node->burst[slot][0] = (uint8_t)epoch;
    node->burst[slot][1] = (uint8_t)from;
    refill_stages(node);
}

static void end_join(ups_node_t *node, int8_t why)
{
    node->join = why;
    node->burst[0][1] = node->burst[1][1] = 16u;
    note(node, UPS_NOTE_JOIN_FAILED);
}

static void start_request(ups_node_t *node, ups_channel_t *ch, uint16_t now);

static void joined_as(ups_node_t *node, unsigned txnode, uint16_t now)
{
    node->txnode = (uint8_t)txnode;
    node->join = UPS__READY;
    node->mode = (uint8_t)(node->mode & ~UPS__OWE_CLAIM);
    node->burst[0][1] = node->burst[1][1] = 16u;
    node->tx_count = 0u; /* Knocks and Stages still queued are of no use now */
    note(node, UPS_NOTE_JOINED);
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        if (node->channels[i].flags & UPS__PEND) {
            start_request(node, &node->channels[i], now);
        }
    }
}

/** Census, Query, Offer, Assign and the rest, as a joining node hears them. */
static void join_frame(ups_node_t *node, unsigned op, unsigned arg, const uint8_t *data,
                       uint16_t now)
{
    unsigned epoch = arg >> 8;
    unsigned len = (arg >> 4) & 0xFu; /* Query: prefix length - 1 */
    if (op == OP_STATUS && (arg >> 8) == ST_CENSUS) {
        heard(node, now);
        answer_query(node, arg & 0xFu, 0u);
    } else if (op == OP_QUERY) {
        heard(node, now);
        unsigned stage = 0u;
        while (stage <= len && nibble(node->node_id, stage) == nibble(data, stage)) {
            ++stage;
        }
        if (stage > len) {
            answer_query(node, epoch, len + 1u);
        }
    } else if (op == OP_ASSIGN && ups__same8(data, node->node_id)) {
        if (arg & OFFER_BIT) {
            heard(node, now);
            node->txnode = (uint8_t)(arg & 0x7Fu);
            node->mode = (uint8_t)(node->mode | UPS__OWE_CLAIM); /* refill() queues it */
        } else {
            joined_as(node, arg, now);
        }
    } else if (op == OP_STATUS && (arg >> 8) == ST_KNOCK) {
        node->t_quiet = now; /* another joiner's Knock: on a real bus it is ours too */
    } else if (op == OP_STATUS && (arg >> 8) == ST_HELLO) {
        knock(node, now); /* a CAN-ECB has just started: it takes knocks at once */
    } else if (op == OP_STATUS && (arg >> 8) == ST_TXNODES_FULL &&
               ups__same8(data, node->node_id)) {
        end_join(node, UPS_ERR_TXNODES_FULL);
    } else if (op == OP_STATUS && (arg >> 8) == ST_FAILED && ups__same8(data, node->node_id)) {
        end_join(node, UPS_ERR_FAILED);
    }
}

/* ---- binding ------------------------------------------------------------------------------- */

static inline unsigned wanted_class(const ups_channel_t *ch)
{
    return (unsigned)ch->step >> 4;
}

/** The request the channel's roles ask: SUB_BIND for a subscriber of one-frame events, else
 *  PUB_BIND, or PUB_BIND(c) for a size class above 0. */
static unsigned request_kind(const ups_channel_t *ch)
{
    unsigned cls = wanted_class(ch);
    if (!(ch->flags & UPS__PUB) || (cls == 0u && (ch->flags & UPS__SUB))) {
        return RQ_SUB_BIND;
    }
    return cls > 0u ? RQ_PUB_BIND_CLASS + cls : RQ_PUB_BIND;
}

/** Whether the channel's request is a PUB_BIND (else SUB_BIND). */
static inline int asks_pub(const ups_channel_t *ch)
{
    return request_kind(ch) != RQ_SUB_BIND;
}

static void send_request(ups_node_t *node, ups_channel_t *ch, uint16_t now)
{
    ch->t0 = now;
    push_request(node, 0u, request_kind(ch), ch->uid);
}

/** The roles of a channel waiting for its etag changed, and with them the request (it was
 *  @p asked): an answer to the old one would not tell the CAN-ECB the new role (a subscriber
 *  added to a PUB_BIND, a publisher left alone with a SUB_BIND), so only an answer to the new
 *  request counts, and the request retry sends it at the next tick. */
static void reask(ups_channel_t *ch, unsigned asked)
{
    if ((ch->flags & UPS__PEND) && request_kind(ch) != asked) {
        ch->flags = (uint8_t)(ch->flags & ~(UPS__ASKED | UPS__CAND));
        ch->etag = 0u;
        ch->step = (uint8_t)(ch->step & 0xF0u);
        ch->t0 = (uint16_t)(ch->t0 - RETRY_MAX); /* due at once */
    }
}

/** The node stops relying on @p etag: what is queued on it does not go out (by the time it
 *  would, the etag may be another channel's), nor does the rest of a transfer on it, and no
 *  transfer begun on it is finished (contradiction rule 1). */
static void drop_etag(ups_node_t *node, uint16_t etag)
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

/** Ask for the channel's etag now, and from now on by the request retry. */
static void start_request(ups_node_t *node, ups_channel_t *ch, uint16_t now)
{
    if (ch->flags & UPS__BOUND) {
        drop_etag(node, ch->etag);
        note(node, (ch->flags & UPS__SUB) ? UPS_NOTE_FILTERS | UPS_NOTE_CHANNELS
                                          : UPS_NOTE_CHANNELS); /* the old filter goes first */
    }
    ch->flags = (uint8_t)((ch->flags | UPS__PEND) &
                          ~(UPS__ASKED | UPS__CAND | UPS__BOUND | UPS__WAIT));
    ch->etag = 0u;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    ch->state = UPS__WAITING;
    if (joined(node)) {
        send_request(node, ch, now);
    }
}

/** SUB_AT (priority 0x00) or PUB_AT (0x01): the node holds the channel at its etag. */
static void send_holds(ups_node_t *node, const ups_channel_t *ch, int publish)
{
    push_request(node, publish ? 1u : 0u, ch->etag, ch->uid);
}

static void fail(ups_node_t *node, ups_channel_t *ch, int8_t why)
{
    if (ch->flags & UPS__REBIND) {
        return; /* maybe stray: a channel being bound again keeps asking (request retry) */
    }
    ch->flags = (uint8_t)(ch->flags & ~(UPS__PEND | UPS__ASKED | UPS__CAND));
    ch->state = why;
    note(node, UPS_NOTE_CHANNELS);
}

/** Rely on @p etag for @p ch from now on. */
static void adopt(ups_node_t *node, ups_channel_t *ch, uint16_t etag, uint16_t now)
{
    unsigned cls = ups__class(etag);
    ch->flags = (uint8_t)((ch->flags | UPS__BOUND) & ~(UPS__PEND | UPS__ASKED | UPS__CAND |
                                                       UPS__REBIND | UPS__WAIT));
    ch->etag = etag;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    ch->state = UPS__READY;
    note(node, UPS_NOTE_CHANNELS);
    int asked_pub = asks_pub(ch);
    if ((ch->flags & UPS__SUB) && ups__class_max(cls) > UPS_MAX_EVENT) {
        ch->owe = (uint8_t)(ch->owe | UPS__OWE_UNSUB); /* it would not fit: do not subscribe */
        if (!(ch->flags & UPS__PUB)) { /* the entry stays, in error, until ups_unsubscribe */
            ch->flags = (uint8_t)(ch->flags & ~UPS__BOUND);
            ch->etag = 0u;
            ch->state = UPS_ERR_TOO_LARGE;
            return;
        }
        ch->flags = (uint8_t)(ch->flags & ~UPS__SUB);
    }
    if (ch->flags & UPS__SUB) {
        note(node, UPS_NOTE_FILTERS);
        if (asked_pub) {
            ch->owe = (uint8_t)(ch->owe | UPS__OWE_SUB_AT);
        }
    }
    if ((ch->flags & UPS__PUB) && !asked_pub) {
        ch->owe = (uint8_t)(ch->owe | UPS__OWE_PUB_AT);
    }
    if ((ch->flags & UPS__PUB) && cls > 0u) {
        ch->flags = (uint8_t)(ch->flags | UPS__WAIT); /* subscribers re-bind after a move */
        ch->t0 = now;
        ch->state = UPS__WAITING;
    }
}

/** A Bind contradicted the channel's binding: stop relying on it and ask again. */
static void contradicted(ups_node_t *node, ups_channel_t *ch, uint16_t now)
{
    ch->flags = (uint8_t)(ch->flags | UPS__REBIND);
    start_request(node, ch, now);
}

#if UPS_HEARD_BINDS
/** Remember Bind(etag, uid); return 1 when the etag was last heard bound to another UID. */
static int heard_other(ups_node_t *node, uint16_t etag, const uint8_t *uid)
{
    int other = 0;
    unsigned at = node->heard_next;
    for (unsigned i = 0; i < UPS_HEARD_BINDS; ++i) {
        if (node->heard_etag[i] == etag) {
            other = !ups__same8(node->heard_uid[i], uid);
            at = i;
            break;
        }
    }
    if (at == node->heard_next) {
        node->heard_next = (uint8_t)(at + 1u < UPS_HEARD_BINDS ? at + 1u : 0u);
    }
    node->heard_etag[at] = etag;
    ups__copy(node->heard_uid[at], uid, 8u);
    return other;
}

static int heard_etag(const ups_node_t *node, uint16_t etag)
{
    for (unsigned i = 0; i < UPS_HEARD_BINDS; ++i) {
        if (node->heard_etag[i] == etag) {
            return 1;
        }
    }
    return 0;
}
#endif

/** Bind(etag, uid), from the CAN-ECB or anyone: the contradiction rule, then answers. */
static void on_bind(ups_node_t *node, uint16_t etag, const uint8_t *uid, uint16_t now)
{
#if UPS_HEARD_BINDS
    int doubt = heard_other(node, etag, uid);
#else
    int doubt = 0;
#endif
    int contradiction = 0;
    int grows = 0;     /* the Bind moves one of our channels to a larger size class ... */
    int etag_ours = 0; /* ... and names no etag of ours: a move, not a contradiction */
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        ups_channel_t *ch = &node->channels[i];
        int same_etag = ch->etag == etag;
        int same_uid = ups__same8(ch->uid, uid);
        if ((ch->flags & UPS__CAND) && same_etag != same_uid) {
            start_request(node, ch, now); /* the candidate is spoiled: ask for a fresh answer */
        } else if ((ch->flags & UPS__BOUND) && same_etag != same_uid) {
            grows |= same_uid && ups__class(etag) > ups__class(ch->etag);
            etag_ours |= same_etag;
            contradicted(node, ch, now);
            contradiction = 1;
        }
    }
    if (contradiction) {
        ups__count(grows && !etag_ours ? &node->counters.moves : &node->counters.rebinds);
        return; /* adopt nothing from it */
    }
    int i = find_uid(node, uid);
    if (i < 0) {
        return;
    }
    ups_channel_t *ch = &node->channels[i];
    unsigned expected = UPS__PEND | UPS__ASKED;
    if ((ch->flags & (expected | UPS__CAND)) != expected || ups__class(etag) < wanted_class(ch)) {
        return; /* not asked (yet), settling already, or for a smaller class than ours */
    }
    if (doubt) {
        ups__count(&node->counters.rebinds); /* adopt it when it comes again */
    } else if (ch->flags & UPS__REBIND) {
        ch->flags = (uint8_t)(ch->flags | UPS__CAND);
        ch->etag = etag;
        ch->t0 = now;
    } else {
        adopt(node, ch, etag, now);
    }
}

/* ---- Hello answers ------------------------------------------------------------------------- */

#if UPS_DECLARATIONS
static ups_declaration_t *declaration_of(ups_node_t *node, unsigned channel)
{
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
        if (node->decl[i].channel == channel) {
            return &node->decl[i];
        }
    }
    return NULL;
}

static void send_declare(ups_node_t *node, const ups_declaration_t *decl, uint16_t etag)
{
    uint8_t data[8] = {(uint8_t)(etag >> 8), (uint8_t)etag, decl->size,
                       (uint8_t)(decl->period >> 8), (uint8_t)decl->period,
                       (uint8_t)(decl->deadline >> 8), (uint8_t)decl->deadline, decl->jitter};
    push_request(node, 0u, RQ_DECLARE, data);
}
#endif

/** The answer to Hello: CLAIM, then SUB_AT/PUB_AT of every channel relied on when its frame
 *  goes, then DECLARE of every admitted stream (queue_owed() keeps that order). */
static void start_announcing(ups_node_t *node, uint16_t now)
{
    node->mode = (uint8_t)((node->mode | UPS__OWE_CLAIM | UPS__RECENT) & ~UPS__ANNOUNCE_DUE);
    node->t_announce = now;
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        ups_channel_t *ch = &node->channels[i];
        unsigned owe = UPS__OWE_DECLARE;
        if (ch->flags & UPS__SUB) {
            owe |= UPS__OWE_SUB_AT;
        }
        if (ch->flags & UPS__PUB) {
            owe |= UPS__OWE_PUB_AT;
        }
        ch->owe = (uint8_t)(ch->owe | owe);
    }
}

static void on_hello(ups_node_t *node, uint16_t now)
{
    if (node->mode & UPS__RECENT) {
        node->mode = (uint8_t)(node->mode | UPS__ANNOUNCE_DUE); /* when the second has passed */
    } else {
        start_announcing(node, now);
    }
}

/** Queue owed frame @p bit of channel @p i; 0 when it is owed no more (a SUB_AT, PUB_AT or
 *  DECLARE reports only a binding the node relies on at this moment, and an admitted stream). */
static int queue_one(ups_node_t *node, unsigned i, unsigned bit)
{
    ups_channel_t *ch = &node->channels[i];
    if (bit == UPS__OWE_UNSUB) {
        push_request(node, 0u, RQ_UNSUB, ch->uid);
        return 1;
    }
    if (!(ch->flags & UPS__BOUND)) {
        return 0;
    }
    if (bit == UPS__OWE_SUB_AT || bit == UPS__OWE_PUB_AT) {
        int publish = bit == UPS__OWE_PUB_AT;
        if (!(ch->flags & (publish ? UPS__PUB : UPS__SUB))) {
            return 0;
        }
        send_holds(node, ch, publish);
        return 1;
    }
#if UPS_DECLARATIONS
    const ups_declaration_t *decl = declaration_of(node, i);
    if (decl != NULL && decl->state == UPS__READY) {
        send_declare(node, decl, ch->etag);
        return 1;
    }
#endif
    return 0;
}

/** Queue the next owed frame, if any: the CLAIM, then every SUB_AT and PUB_AT, then DECLARE
 *  and UNSUB. Returns 1 when it queued one. */
static int queue_owed(ups_node_t *node)
{
    if (node->mode & UPS__OWE_CLAIM) {
        node->mode = (uint8_t)(node->mode & ~UPS__OWE_CLAIM);
        push_request(node, 0u, RQ_CLAIM, node->node_id);
        return 1;
    }
    for (unsigned mask = UPS__OWE_SUB_AT | UPS__OWE_PUB_AT; mask < 0x10u; mask <<= 2) {
        for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
            ups_channel_t *ch = &node->channels[i];
            while (ch->owe & mask) {
                unsigned owed = ch->owe & mask;
                unsigned bit = owed & (0u - owed); /* the lowest */
                ch->owe = (uint8_t)(ch->owe & ~bit);
                if (queue_one(node, i, bit)) {
                    return 1;
                }
            }
        }
    }
    return 0;
}

/** Assign(t', this node's id) with another TxNode: move at once and announce. */
static void move_to(ups_node_t *node, unsigned txnode, uint16_t now)
{
    uint32_t old = (uint32_t)node->txnode << UPS__TXNODE_SHIFT;
    uint32_t mask = UPS__MGMT << UPS__TXNODE_SHIFT;
    for (unsigned i = 0; i < node->tx_count; ++i) { /* same TxNode for all: order is kept */
        if ((node->tx[i].id & mask) == old) {
            node->tx[i].id = (node->tx[i].id & ~mask) | ((uint32_t)txnode << UPS__TXNODE_SHIFT);
        }
    }
#if UPS_WITH_TRANSFERS
    if ((node->tx_id & mask) == old) {
        node->tx_id = (node->tx_id & ~mask) | ((uint32_t)txnode << UPS__TXNODE_SHIFT);
    }
#endif
    node->txnode = (uint8_t)txnode;
    ups__count(&node->counters.moves);
    note(node, UPS_NOTE_JOINED);
    start_announcing(node, now);
}

/* ---- declarations -------------------------------------------------------------------------- */

#if UPS_DECLARATIONS
/** Grant or Refuse for this node's stream on @p etag. */
static void on_verdict(ups_node_t *node, uint16_t etag, int granted, uint8_t priority)
{
    int i = -1;
    for (unsigned c = 0; i < 0 && c < UPS_CHANNELS; ++c) {
        if ((node->channels[c].flags & UPS__BOUND) && node->channels[c].etag == etag) {
            i = (int)c;
        }
    }
    if (i < 0) {
        return;
    }
    ups_declaration_t *decl = declaration_of(node, (unsigned)i);
    if (granted) {
        node->channels[i].priority = priority; /* also unasked: another declaration moved it */
        if (decl != NULL) {
            decl->state = UPS__READY;
            note(node, UPS_NOTE_DECLARATIONS);
        }
    } else if (decl != NULL && decl->state == UPS__WAITING) {
        decl->state = UPS_ERR_REFUSED;
        note(node, UPS_NOTE_DECLARATIONS);
    }
}
#endif

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
        int i = find_uid(node, data);
        if (joined(node) && low == node->txnode && i >= 0 &&
            (node->channels[i].flags & UPS__PEND)) {
            fail(node, &node->channels[i], UPS_ERR_LIMIT);
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
            on_verdict(node, etag, status == ST_GRANT, data[3]);
        }
#endif
        return 1;
    }
    if (!joined(node)) {
        return 1; /* Hello, TxNodesFull, Failed while joining: join_frame() */
    }
    int i = find_uid(node, data);
    if (status == ST_HELLO) {
        on_hello(node, now);
    } else if ((status == ST_ETAGS_FULL || status == ST_FAILED) && i >= 0 &&
               (node->channels[i].flags & UPS__PEND)) {
        fail(node, &node->channels[i], status == ST_FAILED ? UPS_ERR_FAILED : UPS_ERR_ETAGS_FULL);
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
        on_bind(node, etag, data, now);
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
        move_to(node, arg, now);
    }
    if (node->join == UPS__WAITING) {
        join_frame(node, op, arg, data, now);
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
        int known = 0;
        for (unsigned c = 0; c < UPS_CHANNELS; ++c) {
            known |= node->channels[c].etag == etag;
        }
#if UPS_HEARD_BINDS
        known |= heard_etag(node, etag);
#endif
        ups__count(known ? &node->counters.filtered : &node->counters.unknown);
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

static void tick_channel(ups_node_t *node, ups_channel_t *ch, uint16_t now)
{
    uint16_t waited = ups__since(now, ch->t0);
    if (ch->flags & UPS__CAND) {
        if (waited >= SETTLE) {
            adopt(node, ch, ch->etag, now); /* it stood 50 ms with nothing contradicting it */
        }
    } else if (ch->flags & UPS__PEND) {
        unsigned step = ch->step & 0xFu;
        if (waited < retry_delay(step)) {
            return;
        }
        if (step >= RETRY_STEPS && !(ch->flags & UPS__REBIND)) {
            fail(node, ch, UPS_ERR_TIMEOUT);
            return;
        }
        ch->step = (uint8_t)((ch->step & 0xF0u) | (step < RETRY_STEPS ? step + 1u : step));
        send_request(node, ch, now);
    } else if ((ch->flags & UPS__WAIT) && waited >= GROW_PAUSE) {
        ch->flags = (uint8_t)(ch->flags & ~UPS__WAIT);
        ch->state = UPS__READY;
        note(node, UPS_NOTE_CHANNELS);
    }
}

#if UPS_DECLARATIONS
static void tick_declaration(ups_node_t *node, ups_declaration_t *decl, uint16_t now)
{
    if (decl->channel >= UPS_CHANNELS || decl->state != UPS__WAITING ||
        ups__since(now, decl->t0) < retry_delay(decl->step)) {
        return;
    }
    const ups_channel_t *ch = &node->channels[decl->channel];
    if (decl->step >= RETRY_STEPS) {
        decl->state = UPS_ERR_TIMEOUT;
        note(node, UPS_NOTE_DECLARATIONS);
        return;
    }
    decl->step = (uint8_t)(decl->step + 1u);
    decl->t0 = now;
    if (ch->flags & UPS__BOUND) {
        send_declare(node, decl, ch->etag);
    }
}
#endif

static void tick_join(ups_node_t *node, uint32_t now_ms)
{
    uint16_t now = now16(now_ms);
    if (UPS_JOIN_GIVE_UP_MS != 0u && now_ms - node->t_join >= UPS_JOIN_GIVE_UP_MS) {
        end_join(node, UPS_ERR_TIMEOUT);
        return;
    }
    unsigned delay = KNOCK_FIRST << node->knock_step;
    if (ups__since(now, node->t_quiet) >= (delay < KNOCK_MAX ? delay : KNOCK_MAX)) {
        knock(node, now);
        if (node->knock_step < 3u) {
            node->knock_step = (uint8_t)(node->knock_step + 1u);
        }
    }
}

void ups_tick(ups_node_t *node, uint32_t now_ms)
{
    uint16_t now = now16(now_ms);
    if (node->join == UPS__WAITING) {
        tick_join(node, now_ms);
    } else if (joined(node)) {
        for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
            tick_channel(node, &node->channels[i], now);
        }
#if UPS_DECLARATIONS
        for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
            tick_declaration(node, &node->decl[i], now);
        }
#endif
        if ((node->mode & UPS__RECENT) && ups__since(now, node->t_announce) >= HELLO_GAP) {
            node->mode = (uint8_t)(node->mode & ~UPS__RECENT);
        }
        if ((node->mode & (UPS__ANNOUNCE_DUE | UPS__RECENT)) == UPS__ANNOUNCE_DUE) {
            start_announcing(node, now);
        }
        /* one owed frame at a time, paced, once the management frames before it are sent */
        if (node->tx_count < UPS_TX_DEPTH &&
            (node->tx_count == 0u || node->tx[0].id >= UPS__FIRST_EVENT_ID) &&
            ups__since(now, node->t_pace) >= ANNOUNCE_PACE && queue_owed(node)) {
            node->t_pace = now;
        }
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
    put64(node->node_id, node_id);
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

void ups_start(ups_node_t *node, uint32_t now_ms)
{
    if (joined(node)) {
        return;
    }
    node->join = UPS__WAITING;
    node->txnode = UPS__MGMT;
    node->mode = (uint8_t)(node->mode & ~UPS__OWE_CLAIM);
    node->t_join = now_ms;
    node->knock_step = 0u;
    knock(node, now16(now_ms));
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
        int i = find_uid(node, sent->data);
        if (i >= 0) { /* the request its roles ask now is sent: Binds from now on may answer */
            ups_channel_t *ch = &node->channels[i];
            if ((ch->flags & UPS__PEND) && (sent->id & UPS__ETAG_MASK) == request_kind(ch)) {
                ch->flags = (uint8_t)(ch->flags | UPS__ASKED);
            }
        }
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

/** The channel of @p uid with @p role added, or a new one; its index or UPS_ERR_FULL. */
static int add_role(ups_node_t *node, uint64_t uid, uint8_t role, unsigned cls, uint16_t now)
{
    uint8_t raw[8];
    put64(raw, uid);
    int i = find_uid(node, raw);
    if (i < 0) {
        for (i = 0; i < UPS_CHANNELS && (node->channels[i].flags | node->channels[i].owe) != 0u;
             ++i) {
        }
        if (i == UPS_CHANNELS) {
            return UPS_ERR_FULL;
        }
        ups__copy(node->channels[i].uid, raw, 8u);
    }
    ups_channel_t *ch = &node->channels[i];
    if (role == UPS__SUB) {
        ch->owe = (uint8_t)(ch->owe & ~UPS__OWE_UNSUB); /* back before its UNSUB went */
    }
    if (ch->flags == 0u) { /* a new entry, or one whose UNSUB was still owed */
        ch->priority = UPS__DEFAULT_PRIORITY;
        ch->flags = role;
        ch->step = (uint8_t)(cls << 4);
        start_request(node, ch, now);
        return i;
    }
    uint8_t had = ch->flags;
    unsigned asked = request_kind(ch);
    ch->flags = (uint8_t)(ch->flags | role);
    if (cls > wanted_class(ch)) {
        ch->step = (uint8_t)((ch->step & 0x0Fu) | (cls << 4));
    }
    reask(ch, asked);
    if (ch->state < 0 || ((had & UPS__BOUND) && ups__class(ch->etag) < wanted_class(ch))) {
        start_request(node, ch, now); /* it failed before, or it moves to a larger size class */
    } else if ((had & UPS__BOUND) && !(had & role)) {
        ch->owe = (uint8_t)(ch->owe | (role == UPS__PUB ? UPS__OWE_PUB_AT : UPS__OWE_SUB_AT));
        note(node, UPS_NOTE_FILTERS | UPS_NOTE_CHANNELS);
    }
    return i;
}

int ups_subscribe(ups_node_t *node, uint64_t uid, uint32_t now_ms)
{
    return add_role(node, uid, UPS__SUB, 0u, now16(now_ms));
}

int ups_advertise(ups_node_t *node, uint64_t uid, uint16_t max_size, uint32_t now_ms)
{
    if (max_size > UPS_MAX_EVENT) {
        return UPS_ERR_TOO_LARGE;
    }
    unsigned cls = 0u;
    while (ups__class_max(cls) < max_size) {
        ++cls;
    }
    return add_role(node, uid, UPS__PUB, cls, now16(now_ms));
}

int ups_unsubscribe(ups_node_t *node, int channel)
{
    if (!valid_channel(node, channel)) {
        return UPS_ERR_ARGUMENT;
    }
    ups_channel_t *ch = &node->channels[channel];
    if (ch->flags & UPS__SUB) {
        unsigned asked = request_kind(ch);
        ch->flags = (uint8_t)(ch->flags & ~UPS__SUB);
        reask(ch, asked);
        note(node, UPS_NOTE_FILTERS);
        if (joined(node)) {
            ch->owe = (uint8_t)(ch->owe | UPS__OWE_UNSUB);
        }
    }
    if (!(ch->flags & UPS__PUB)) { /* free once its UNSUB is queued (no declaration: no PUB) */
        ch->flags = 0u;
        ch->etag = 0u;
        ch->state = UPS__FREE;
        ch->owe = (uint8_t)(ch->owe & UPS__OWE_UNSUB);
    }
    return UPS_OK;
}

int ups_publish(ups_node_t *node, int channel, const uint8_t *data, uint16_t size)
{
    if (!valid_channel(node, channel) || (data == NULL && size > 0u)) {
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

int ups_set_priority(ups_node_t *node, int channel, uint8_t priority)
{
    if (!valid_channel(node, channel)) {
        return UPS_ERR_ARGUMENT;
    }
    node->channels[channel].priority = priority < 2u ? 2u : priority;
    return UPS_OK;
}

int ups_channel_state(const ups_node_t *node, int channel)
{
    return channel >= 0 && channel < UPS_CHANNELS ? node->channels[channel].state : UPS__FREE;
}

uint16_t ups_channel_etag(const ups_node_t *node, int channel)
{
    if (!valid_channel(node, channel) || !(node->channels[channel].flags & UPS__BOUND)) {
        return 0u;
    }
    return node->channels[channel].etag;
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

int ups_declare(ups_node_t *node, int channel, uint8_t size, uint16_t period, uint16_t deadline,
                uint8_t jitter, uint32_t now_ms)
{
#if UPS_DECLARATIONS
    if (!valid_channel(node, channel) || !(node->channels[channel].flags & UPS__PUB) ||
        period == 0u || deadline == 0u) {
        return UPS_ERR_ARGUMENT;
    }
    const ups_channel_t *ch = &node->channels[channel];
    if (!(ch->flags & UPS__BOUND) || !joined(node)) {
        return UPS_ERR_UNBOUND;
    }
    if (ch->etag < UPS__LARGE_ETAG ? size > 8u : size == 0u) {
        return UPS_ERR_ARGUMENT;
    }
    ups_declaration_t *decl = declaration_of(node, (unsigned)channel);
    if (decl == NULL) {
        decl = declaration_of(node, 0xFFu);
    }
    if (decl == NULL) {
        return UPS_ERR_FULL;
    }
    decl->channel = (uint8_t)channel;
    decl->state = UPS__WAITING;
    decl->step = 0u;
    decl->size = size;
    decl->period = period;
    decl->deadline = deadline;
    decl->jitter = jitter;
    decl->t0 = now16(now_ms);
    send_declare(node, decl, ch->etag);
    return UPS_OK;
#else
    (void)node, (void)channel, (void)size, (void)period, (void)deadline, (void)jitter;
    (void)now_ms;
    return UPS_ERR_FULL;
#endif
}

int ups_declaration_state(const ups_node_t *node, int channel)
{
#if UPS_DECLARATIONS
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
        if (channel >= 0 && node->decl[i].channel == (unsigned)channel) {
            return node->decl[i].state;
        }
    }
#else
    (void)node, (void)channel;
#endif
    return 0;
}

const ups_counters_t *ups_counters(const ups_node_t *node)
{
    return &node->counters;
}
