/*
 * libups: the join and the answer to Hello (docs/protocol.md, "Joining" and "Restarts, recovery
 * and the answer to Hello").
 *
 * A joining node knocks, answers the CAN-ECB's Census and Query with Stage frames, claims the
 * TxNode an Offer names and is joined by the Assign of its id; a joined node moves when an
 * Assign gives its id another TxNode. Every frame of TxNode 0x7F that ups.c found well formed
 * comes here (ups__config_frame), for the joining and the joined node alike. A TxNodesFull or
 * Failed of its id (anyone can send one) ends the join only once it stood the refusal wait with
 * no Offer or Assign of the id (ups__tick_join).
 *
 * A joined node answers Hello (at most once a second) with CLAIM, then SUB_AT/PUB_AT of the
 * bindings it relies on and DECLARE of its admitted streams. Those are *owed* (a bit of the
 * node for the CLAIM, bits of its channels for the rest) and queued one at a time, paced, once
 * the management frames before them are sent (ups__tick_hello; the channels' own frames are
 * queued by ups__queue_owed in ups_bind.c): a full queue never loses them, and the queue's order
 * by identifier never puts one before a frame it depends on.
 */
#include "ups_bind.h"
#include "ups_join.h"
#include "ups_util.h"

/* timers, in milliseconds (docs/protocol.md, "Timers") */
#define KNOCK_FIRST 300u
#define KNOCK_MAX 2000u
#define HELLO_GAP 1000u
#define REFUSAL_WAIT 3000u
#define ANNOUNCE_PACE 1u

/* ---- joining ------------------------------------------------------------------------------- */

static void push_config(ups_node_t *node, uint32_t arg, const uint8_t *data, unsigned len)
{
    (void)ups__push(node, ups__make_id(0u, UPS__MGMT, arg), 0u, data, len);
}

static void knock(ups_node_t *node, uint32_t now)
{
    node->t_quiet = now16(now);
    push_config(node, (OP_STATUS << 12) | (ST_KNOCK << 8), NULL, 0u);
}

/** A Census, Query or Offer: the CAN-ECB is at work, no Knock needed for a while. */
static void heard(ups_node_t *node, uint32_t now)
{
    node->t_quiet = now16(now);
    node->knock_step = 0u;
}

/** Queue Stage answers while there is room (a Census asks for 16 frames at once). */
static void refill_stages(ups_node_t *node)
{
    for (unsigned b = 0; b < 2u; ++b) {
        uint8_t *burst = node->burst[b];
        while (burst[1] < 16u && node->tx_count < UPS_TX_DEPTH) {
            unsigned stage = burst[1];
            unsigned arg = ((unsigned)burst[0] << 8) | (stage << 4) |
                           ups__nibble(node->node_id, stage);
            push_config(node, arg, NULL, 0u); /* Stage: op 0 */
            burst[1] = (uint8_t)(stage + 1u);
        }
    }
}

/** Queue the CLAIM owed (of an Offer: from the offered TxNode; in the answer to Hello: from
 *  its own); 1 when it was owed. The queue has room. */
static int claim(ups_node_t *node)
{
    if (!(node->mode & UPS__OWE_CLAIM)) {
        return 0;
    }
    node->mode = (uint8_t)(node->mode & ~UPS__OWE_CLAIM);
    ups__push_request(node, 0u, RQ_CLAIM, node->node_id);
    return 1;
}

/** The frames of the join as room appears: the CLAIM of an Offer first, then Stage answers. */
void ups__join_refill(ups_node_t *node)
{
    if (node->tx_count < UPS_TX_DEPTH) {
        (void)claim(node);
    }
    refill_stages(node);
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

static void joined_as(ups_node_t *node, unsigned txnode)
{
    node->txnode = (uint8_t)txnode;
    node->join = UPS_JOIN_JOINED;
    node->mode = (uint8_t)(node->mode & ~(UPS__OWE_CLAIM | UPS__REFUSED | UPS__REFUSED_FAILED));
    node->burst[0][1] = node->burst[1][1] = 16u;
    node->tx_count = 0u; /* Knocks and Stages still queued are of no use now */
    note(node, UPS_NOTE_JOINED); /* the channels' requests, owed meanwhile, go now */
}

void ups_start(ups_node_t *node, uint32_t now_ms)
{
    if (joined(node)) {
        return;
    }
    node->join = UPS_JOIN_JOINING;
    node->txnode = UPS__MGMT;
    node->mode = (uint8_t)(node->mode & ~(UPS__OWE_CLAIM | UPS__REFUSED | UPS__REFUSED_FAILED));
    node->t_join = now16(now_ms);
    node->knock_step = 0u;
    knock(node, now16(now_ms));
    note(node, UPS_NOTE_FILTERS); /* the first programming: before the Knock goes out */
}

/* ---- the answer to Hello, and moves -------------------------------------------------------- */

/** The answer to Hello: CLAIM, then SUB_AT/PUB_AT of every channel relied on when its frame
 *  goes, then DECLARE of every admitted stream (queue_owed() keeps that order). */
static void start_announcing(ups_node_t *node, uint32_t now)
{
    node->mode = (uint8_t)((node->mode | UPS__OWE_CLAIM | UPS__RECENT) & ~UPS__ANNOUNCE_DUE);
    node->t_announce = now16(now);
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) { /* sent only if relied on then */
        ups_channel_t *ch = &node->channels[i];
        ch->owe = (uint8_t)(ch->owe | UPS__OWE_DECLARE | (ch->flags & (UPS__SUB | UPS__PUB)) << 1);
    }
}

/** Assign(t', this node's id) with another TxNode: move at once and announce. */
static void move_to(ups_node_t *node, unsigned txnode, uint32_t now)
{
    uint32_t mask = UPS__MGMT << UPS__TXNODE_SHIFT;
    uint32_t to = (uint32_t)txnode << UPS__TXNODE_SHIFT;
    for (unsigned i = 0; i < node->tx_count; ++i) { /* all from its TxNode: order is kept */
        node->tx[i].id = (node->tx[i].id & ~mask) | to;
    }
#if UPS_WITH_TRANSFERS
    node->tx_id = (node->tx_id & ~mask) | to;
#endif
    node->txnode = (uint8_t)txnode;
    ups__count(&node->counters.moves);
    note(node, UPS_NOTE_JOINED);
    start_announcing(node, now);
}

static void on_hello(ups_node_t *node, uint32_t now)
{
    if (node->mode & UPS__RECENT) {
        node->mode = (uint8_t)(node->mode | UPS__ANNOUNCE_DUE); /* when the second has passed */
    } else {
        start_announcing(node, now);
    }
}

/* ---- the CAN-ECB's frames ------------------------------------------------------------------ */

/* For each status frame (bits 8-11 of the etag field), the refusal it is when it names a
 * request of this node (-UPS_ERR_; 0: none): EtagsFull, Failed, Limit. */
static const uint8_t status_refusal[16] = {0u, 0u, 9u, 0u, 0u, 0u, 0u, 11u, 10u};

void ups__config_frame(ups_node_t *node, unsigned op, unsigned arg, const uint8_t *data,
                       uint32_t now)
{
    unsigned status = arg >> 8;
    unsigned low = arg & 0xFFu;
    int joining = node->join == UPS_JOIN_JOINING; /* else joined */
    if (op == OP_ASSIGN) { /* Offer or Assign */
        if (!ups__same8(data, node->node_id)) {
            return;
        }
        if (!joining) {
            if (arg < UPS__MGMT && arg != node->txnode) {
                move_to(node, arg, now); /* Assign(t', its id): the old one is another's */
            } else if (arg == node->txnode) {
                on_hello(node, now); /* its own again: the CAN-ECB forgot its channels */
            }
        } else if (arg & OFFER_BIT) {
            heard(node, now);
            node->txnode = (uint8_t)(arg & 0x7Fu);
            node->mode = (uint8_t)((node->mode | UPS__OWE_CLAIM) & /* refill() queues it */
                                   ~(UPS__REFUSED | UPS__REFUSED_FAILED)); /* a refusal: void */
        } else {
            joined_as(node, arg);
        }
    } else if (!joining) {
        if (op != OP_STATUS) {
            return; /* Stage, Query: for joiners */
        }
        if (status == ST_HELLO) {
            on_hello(node, now);
        }
        if (status_refusal[status] != 0u && (status != ST_LIMIT || low == node->txnode)) {
            ups__refused(node, data, -(int)status_refusal[status], now);
        }
#if UPS_DECLARATIONS
        if ((status == ST_GRANT || status == ST_REFUSE) && data[2] == node->txnode) {
            ups__on_verdict(node, get16(data), status == ST_GRANT, data[3], now);
        }
#endif
    } else if (op == OP_QUERY || (op == OP_STATUS && status == ST_CENSUS)) {
        unsigned epoch = status;                    /* Query(e, P): |P| = l + 1 nibbles ... */
        unsigned from = ((arg >> 4) & 0xFu) + 1u;
        if (op == OP_STATUS) {
            epoch = low; /* ... Census(e): the empty prefix */
            from = 0u;
        }
        heard(node, now);
        unsigned s = 0u;
        while (s < from && ups__nibble(node->node_id, s) == ups__nibble(data, s)) {
            ++s;
        }
        if (s == from) { /* its id begins with the prefix: the rest of it */
            answer_query(node, epoch, from);
        }
    } else if (op != OP_STATUS) {
        return; /* another joiner's Stage */
    } else if (status == ST_HELLO) {
        knock(node, now); /* a CAN-ECB has just started: it takes knocks at once */
    } else if (status == ST_KNOCK) {
        if (!(node->mode & UPS__REFUSED)) { /* (a refusal's wait goes on) */
            node->t_quiet = now16(now); /* another joiner's Knock: on a real bus it is ours */
        }
    } else if (((1u << status) & ((1u << ST_TXNODES_FULL) | (1u << ST_FAILED))) &&
               ups__same8(data, node->node_id)) {
        /* a refusal, anyone's: it ends the join once it stood the refusal wait (tick_join) */
        if (!(node->mode & UPS__REFUSED)) {
            node->t_quiet = now16(now);
        }
        node->mode = (uint8_t)((node->mode & ~UPS__REFUSED_FAILED) | UPS__REFUSED |
                               (status == ST_FAILED ? UPS__REFUSED_FAILED : 0u));
    }
}

/* ---- the timers --------------------------------------------------------------------------- */

/** The knock retry, the refusal wait and the give-up. While a refusal is open (TxNodesFull
 *  or Failed of its id, no Offer or Assign of its id since) the node does not knock, and
 *  t_quiet holds when the refusal came or the last Hello, Census or Query after it: the
 *  refusal stands 3 s from then, and ends the join with its error, as does the give-up. */
void ups__tick_join(ups_node_t *node, uint32_t now)
{
    unsigned mode = node->mode;
    unsigned delay = KNOCK_FIRST << node->knock_step;
    int8_t why = UPS_ERR_TIMEOUT;
    if (delay > KNOCK_MAX) {
        delay = KNOCK_MAX;
    }
    if (mode & UPS__REFUSED) {
        why = (mode & UPS__REFUSED_FAILED) ? UPS_ERR_FAILED : UPS_ERR_TXNODES_FULL;
        delay = REFUSAL_WAIT; /* no knock: a census it started would only refuse it again */
    }
    int quiet = ups__since(now, node->t_quiet) >= delay;
    if ((quiet && (mode & UPS__REFUSED)) ||
        (UPS_JOIN_GIVE_UP_MS != 0u && ups__since(now, node->t_join) >= UPS_JOIN_GIVE_UP_MS)) {
        end_join(node, why); /* the refusal stood, or the give-up came */
    } else if (quiet) {
        knock(node, now);
        if (node->knock_step < 3u) {
            node->knock_step = (uint8_t)(node->knock_step + 1u);
        }
    }
}

/** The Hello answer gap, and one owed frame at a time: paced, and only once the management
 *  frames before it are sent. */
void ups__tick_hello(ups_node_t *node, uint32_t now)
{
    if ((node->mode & UPS__RECENT) && ups__since(now, node->t_announce) >= HELLO_GAP) {
        node->mode = (uint8_t)(node->mode & ~UPS__RECENT);
    }
    if ((node->mode & (UPS__ANNOUNCE_DUE | UPS__RECENT)) == UPS__ANNOUNCE_DUE) {
        start_announcing(node, now);
    }
    if (node->tx_count < UPS_TX_DEPTH &&
        (node->tx_count == 0u || node->tx[0].id >= UPS__FIRST_EVENT_ID) &&
        ups__since(now, node->t_pace) >= ANNOUNCE_PACE &&
        (claim(node) || ups__queue_owed(node, now))) { /* the answer to Hello begins with it */
        node->t_pace = now16(now);
    }
}
