/*
 * libups: binding channels to etags, and real-time declarations (docs/protocol.md, "Binding",
 * "The contradiction rule" and "Real-time channels").
 *
 * A channel asks SUB_BIND, PUB_BIND or PUB_BIND(c) (request_kind) until a Bind answers it: one
 * that names its UID, comes after the request went out, is of a large enough size class, and
 * contradicts no binding the node relies on. A Bind that does contradict one (another UID on an
 * etag it relies on, another etag for a UID it relies on) makes it stop relying on every
 * binding involved and ask again; such a re-binding relies on an answer only once it stood
 * 50 ms uncontradicted (settling), and, with UPS_HEARD_BINDS, an answer naming an etag last
 * heard bound to another UID is doubted until it comes again.
 */
#include "ups_internal.h"

/* timers, in milliseconds (docs/protocol.md, "Timers") */
#define RETRY_FIRST 50u
#define RETRY_MAX 1000u
#define RETRY_STEPS 8u /* 50+100+200+400+800+1000*4 = 5550 ms: the 9th wait gives up (5 s) */
#define SETTLE 50u
#define GROW_PAUSE 150u

static inline unsigned retry_delay(unsigned step)
{
    unsigned delay = RETRY_FIRST << (step < 5u ? step : 5u);
    return delay < RETRY_MAX ? delay : RETRY_MAX;
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

/* ---- requests ------------------------------------------------------------------------------ */

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
    ups__push_request(node, 0u, request_kind(ch), ch->uid);
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

/** Ask for the channel's etag now, and from now on by the request retry. */
static void start_request(ups_node_t *node, ups_channel_t *ch, uint16_t now)
{
    if (ch->flags & UPS__BOUND) {
        ups__drop_etag(node, ch->etag);
        note(node, (ch->flags & UPS__SUB) ? UPS_NOTE_FILTERS | UPS_NOTE_CHANNELS
                                          : UPS_NOTE_CHANNELS); /* the old filter goes first */
    }
    ch->flags = (uint8_t)((ch->flags | UPS__PEND) &
                          ~(UPS__ASKED | UPS__CAND | UPS__BOUND | UPS__WAIT));
    ch->etag = 0u;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    if (joined(node)) {
        send_request(node, ch, now);
    }
}

/** The node is joined: ask for the etag of every channel added meanwhile. */
void ups__start_requests(ups_node_t *node, uint16_t now)
{
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        if (node->channels[i].flags & UPS__PEND) {
            start_request(node, &node->channels[i], now);
        }
    }
}

/** The request @p kind for @p uid went out: if its channel asks just that, Binds from now on
 *  may answer it (a Bind received before the request went does not count). */
void ups__sent_request(ups_node_t *node, unsigned kind, const uint8_t *uid)
{
    int i = find_uid(node, uid);
    if (i >= 0) {
        ups_channel_t *ch = &node->channels[i];
        if ((ch->flags & UPS__PEND) && kind == request_kind(ch)) {
            ch->flags = (uint8_t)(ch->flags | UPS__ASKED);
        }
    }
}

/** The channel's request ended with UPS_ERR_ code @p why, kept in the retry step's nibble (a
 *  channel in use that neither waits nor is bound has failed: see ups_channel_state). */
static void fail(ups_node_t *node, ups_channel_t *ch, int why)
{
    if (ch->flags & UPS__REBIND) {
        return; /* maybe stray: a channel being bound again keeps asking (request retry) */
    }
    ch->flags = (uint8_t)(ch->flags & ~(UPS__PEND | UPS__ASKED | UPS__CAND | UPS__BOUND));
    ch->step = (uint8_t)((ch->step & 0xF0u) | (unsigned)-why);
    note(node, UPS_NOTE_CHANNELS);
}

/** EtagsFull, Failed or Limit for @p uid: the request of its channel, if one waits, ends. */
void ups__refused(ups_node_t *node, const uint8_t *uid, int why)
{
    int i = find_uid(node, uid);
    if (i >= 0 && (node->channels[i].flags & UPS__PEND)) {
        fail(node, &node->channels[i], why);
    }
}

/* ---- Binds --------------------------------------------------------------------------------- */

/** Rely on @p etag for @p ch from now on. */
static void adopt(ups_node_t *node, ups_channel_t *ch, uint16_t etag, uint16_t now)
{
    unsigned cls = ups__class(etag);
    ch->flags = (uint8_t)((ch->flags | UPS__BOUND) & ~(UPS__PEND | UPS__ASKED | UPS__CAND |
                                                       UPS__REBIND | UPS__WAIT));
    ch->etag = etag;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    note(node, UPS_NOTE_CHANNELS);
    int asked_pub = asks_pub(ch);
    if ((ch->flags & UPS__SUB) && ups__class_max(cls) > UPS_MAX_EVENT) {
        ch->owe = (uint8_t)(ch->owe | UPS__OWE_UNSUB); /* it would not fit: do not subscribe */
        if (!(ch->flags & UPS__PUB)) { /* the entry stays, in error, until ups_unsubscribe */
            ch->etag = 0u;
            fail(node, ch, UPS_ERR_TOO_LARGE);
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

/** Whether @p etag was ever heard bound (to a channel of this node, or, with UPS_HEARD_BINDS,
 *  to any): an event on it that the node does not receive is filtered, not unknown. */
int ups__etag_known(const ups_node_t *node, uint16_t etag)
{
    int known = 0;
    for (unsigned c = 0; c < UPS_CHANNELS; ++c) {
        known |= node->channels[c].etag == etag;
    }
#if UPS_HEARD_BINDS
    known |= heard_etag(node, etag);
#endif
    return known;
}

/** Bind(etag, uid), from the CAN-ECB or anyone: the contradiction rule, then answers. */
void ups__on_bind(ups_node_t *node, uint16_t etag, const uint8_t *uid, uint16_t now)
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
        note(node, UPS_NOTE_CHANNELS);
    }
}

/* ---- declarations -------------------------------------------------------------------------- */

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
    ups__push_request(node, 0u, RQ_DECLARE, data);
}

/** Grant or Refuse for this node's stream on @p etag. */
void ups__on_verdict(ups_node_t *node, uint16_t etag, int granted, uint8_t priority)
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

/** DECLARE of channel @p i's admitted stream, in the answer to Hello; 0 when it has none. */
int ups__queue_declare(ups_node_t *node, unsigned i)
{
#if UPS_DECLARATIONS
    const ups_declaration_t *decl = declaration_of(node, i);
    if (decl != NULL && decl->state == UPS__READY) {
        send_declare(node, decl, node->channels[i].etag);
        return 1;
    }
#else
    (void)node, (void)i;
#endif
    return 0;
}

/** The request retry, settling, the publisher's pause and the declarations' retry. */
void ups__tick_bind(ups_node_t *node, uint16_t now)
{
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        tick_channel(node, &node->channels[i], now);
    }
#if UPS_DECLARATIONS
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
        tick_declaration(node, &node->decl[i], now);
    }
#endif
}

/* ---- the API ------------------------------------------------------------------------------- */

/** The channel of @p uid with @p role added, or a new one; its index or UPS_ERR_FULL. */
static int add_role(ups_node_t *node, uint64_t uid, uint8_t role, unsigned cls, uint16_t now)
{
    uint8_t raw[8];
    ups__put64(raw, uid);
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
    if (!(had & (UPS__PEND | UPS__CAND | UPS__BOUND)) ||
        ((had & UPS__BOUND) && ups__class(ch->etag) < wanted_class(ch))) {
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
    if (!ups__valid_channel(node, channel)) {
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
        ch->owe = (uint8_t)(ch->owe & UPS__OWE_UNSUB);
    }
    return UPS_OK;
}

int ups_set_priority(ups_node_t *node, int channel, uint8_t priority)
{
    if (!ups__valid_channel(node, channel)) {
        return UPS_ERR_ARGUMENT;
    }
    node->channels[channel].priority = priority < 2u ? 2u : priority;
    return UPS_OK;
}

int ups_channel_state(const ups_node_t *node, int channel)
{
    if (!ups__valid_channel(node, channel)) {
        return UPS__FREE;
    }
    unsigned flags = node->channels[channel].flags;
    if (flags & (UPS__PEND | UPS__CAND | UPS__WAIT)) {
        return UPS__WAITING;
    }
    if (flags & UPS__BOUND) {
        return UPS__READY;
    }
    return -(int)(node->channels[channel].step & 0xFu); /* it failed: fail() */
}

uint16_t ups_channel_etag(const ups_node_t *node, int channel)
{
    if (!ups__valid_channel(node, channel) || !(node->channels[channel].flags & UPS__BOUND)) {
        return 0u;
    }
    return node->channels[channel].etag;
}

int ups_declare(ups_node_t *node, int channel, uint8_t size, uint16_t period, uint16_t deadline,
                uint8_t jitter, uint32_t now_ms)
{
#if UPS_DECLARATIONS
    if (!ups__valid_channel(node, channel) || !(node->channels[channel].flags & UPS__PUB) ||
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
