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
 * heard bound to another UID is doubted until it comes again. A refusal (EtagsFull, Limit,
 * Failed: anyone can send one) ends a request only once it stood 3 s while the node kept
 * asking with no Bind answering it, or when the request gives up with one open; so does a Bind
 * of a size class the node cannot receive (UPS_ERR_TOO_LARGE: anyone can send that too, and
 * the CAN-ECB's answer wins). A channel being bound again after a contradiction takes neither:
 * it keeps asking until a Bind binds it.
 *
 * A declaration takes a Grant or Refuse only once its DECLARE was sent and while its answer is
 * not a Refuse; the answer is the latest verdict once it stood 0.5 s with no other, and after a
 * Grant the stream follows each verdict at once.
 *
 * Every frame a channel sends is *owed* first (a bit of ups_channel_t.owe) and queued by
 * ups__queue_owed() one at a time, when there is room and no management frame waits before it:
 * a full queue never loses a request, SUB_AT, PUB_AT, DECLARE or UNSUB, and the queue's order
 * by identifier never puts a DECLARE before the PUB_AT the CAN-ECB needs first.
 */
#include "ups_bind.h"
#include "ups_transfer.h"
#include "ups_util.h"

/* timers, in milliseconds (docs/protocol.md, "Timers") */
#define RETRY_FIRST 50u
#define RETRY_MAX 1000u
#define RETRY_STEPS 8u /* 50+100+200+400+800+1000*4 = 5550 ms: the 9th wait gives up (5 s) */
#define SETTLE 50u
#define REFUSAL_WAIT 3000u
#define VERDICT_WAIT 500u

/* ups_declaration_t.heard: before the first verdict, then the latest one */
#define HEARD_UNSENT 0u     /* the DECLARE has not been sent: a verdict is not for it */
#define HEARD_NONE 1u       /* sent, no verdict since */
#define HEARD_REFUSE 0x80u  /* Refuse (a Grant's priority is 0x02-0x7F) */
#define GROW_PAUSE 150u

static unsigned retry_delay(unsigned step)
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

/** Verdict @p verdict (a granted priority, or HEARD_REFUSE) for the declared stream of @p ch:
 *  a Grant sets its priority, a Refuse puts it back to the one from before the declaration;
 *  taken as the answer (state 1), a Refuse ends the declaration. */
static void follow(ups_node_t *node, ups_channel_t *ch, ups_declaration_t *decl, unsigned verdict)
{
    if (verdict != HEARD_REFUSE) {
        ch->priority = (uint8_t)verdict;
        decl->state = UPS_DECL_GRANTED;
    } else {
        ch->priority = decl->fallback; /* best effort, until a Grant comes */
        if (decl->state == UPS_DECL_WAITING) {
            decl->state = UPS_ERR_REFUSED; /* over: later verdicts for it are stray */
        }
    }
    note(node, UPS_NOTE_DECLARATIONS);
}
#endif

/* ---- requests ------------------------------------------------------------------------------ */

/** The size class the channel's events need (always 0 without transfers: size classes are
 *  compiled in with them, and the compiler drops what depends on a larger one). */
static unsigned wanted_class(const ups_channel_t *ch)
{
    return UPS_WITH_TRANSFERS ? (unsigned)ch->step >> 4 : 0u;
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

/** Ask for the channel's etag (once joined), and from then on by the request retry; a node
 *  that relied on an etag for it stops, and nothing queued on that etag goes out. */
static void start_request(ups_node_t *node, ups_channel_t *ch)
{
    if (ch->flags & UPS__BOUND) {
        ups__tx_drop(node, 0u, ch->etag);
#if UPS_WITH_TRANSFERS
        ups__transfer_drop(node, ch->etag);
#endif
        note(node, (ch->flags & UPS__SUB) ? UPS_NOTE_FILTERS | UPS_NOTE_CHANNELS
                                          : UPS_NOTE_CHANNELS); /* the old filter goes first */
    }
    ch->flags = (uint8_t)((ch->flags | UPS__PEND) &
                          ~(UPS__ASKED | UPS__CAND | UPS__BOUND | UPS__WAIT));
    ch->etag = 0u;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    ch->owe = (uint8_t)(ch->owe | UPS__OWE_REQUEST);
}

void ups__sent_request(ups_node_t *node, unsigned kind, const uint8_t *uid)
{
#if UPS_DECLARATIONS
    if (kind == RQ_DECLARE) { /* its data: the declaration's, as it was queued */
        for (unsigned d = 0; d < UPS_DECLARATIONS; ++d) {
            ups_declaration_t *decl = &node->decl[d];
            if (decl->heard == HEARD_UNSENT && ups__same8(decl->data, uid)) {
                decl->heard = HEARD_NONE; /* verdicts from now on are for it */
            }
        }
        return;
    }
#endif
    int i = find_uid(node, uid);
    if (i >= 0) {
        ups_channel_t *ch = &node->channels[i];
        if ((ch->flags & UPS__PEND) && kind == request_kind(ch)) {
            ch->flags = (uint8_t)(ch->flags | UPS__ASKED);
        }
    }
}

/** The channel's request ended with UPS_ERR_ code @p why, kept in the retry step's nibble (a
 *  channel in use that neither waits nor is bound has failed: see ups_channel_state). The
 *  channel's events would not fit the node (UPS_ERR_TOO_LARGE): it does not subscribe (UNSUB:
 *  the CAN-ECB took its SUB_BIND), and one that publishes too asks again as a publisher. */
static void fail(ups_node_t *node, ups_channel_t *ch, int why)
{
    if (why == UPS_ERR_TOO_LARGE) {
        ch->owe = (uint8_t)(ch->owe | UPS__OWE_UNSUB);
        if (ch->flags & UPS__PUB) {
            ch->flags = (uint8_t)(ch->flags & ~UPS__SUB);
            start_request(node, ch);
            return;
        }
    }
    ch->flags = (uint8_t)(ch->flags & ~(UPS__PEND | UPS__ASKED | UPS__CAND | UPS__BOUND));
    ch->step = (uint8_t)((ch->step & 0xF0u) | (unsigned)-why);
    note(node, UPS_NOTE_CHANNELS);
}

/* A refusal of a channel's request (EtagsFull, Limit, Failed, or a Bind of a size class the
 * node cannot receive) is open while it waits for its etag: its etag field, free then, holds
 * the latest refusal (bits 12-15: -UPS_ERR_, 4 or 9-11, so the field is at least 0x4000, which
 * no etag of a frame is) and when the first one came (bits 0-11: bits 2-13 of the clock, in
 * 4 ms steps up to 16 s: the request ends within 5.6 s). A Bind that answers the request
 * overwrites it (voids the refusal), and so does a new request. */
#define REFUSAL_SHIFT 12u
#define REFUSAL_TIME 0xFFFu

/** The error of the refusal open on @p ch, or 0. */
static int refusal_of(const ups_channel_t *ch)
{
    return -(int)((unsigned)ch->etag >> REFUSAL_SHIFT);
}

void ups__refused(ups_node_t *node, const uint8_t *uid, int why, uint32_t now)
{
    int i = find_uid(node, uid);
    if (i < 0) {
        return;
    }
    ups_channel_t *ch = &node->channels[i];
    if ((ch->flags & (UPS__PEND | UPS__ASKED | UPS__REBIND)) != (UPS__PEND | UPS__ASKED)) {
        return; /* none asked (yet: no answer to it); or maybe stray: a channel being bound
                   again keeps asking */
    }
    unsigned since = ch->etag != 0u ? ch->etag : now >> 2u; /* the first one's time */
    ch->etag = (uint16_t)((unsigned)-why << REFUSAL_SHIFT | (since & REFUSAL_TIME));
}

/** Queue frame @p bit that channel @p i owes; 0 when it is owed no more: a SUB_AT, PUB_AT or
 *  DECLARE reports only a binding the node relies on now, a request only one it still wants. */
static int queue_one(ups_node_t *node, unsigned i, unsigned bit, uint32_t now)
{
    ups_channel_t *ch = &node->channels[i];
    unsigned priority = 0u;
    unsigned etag = ch->etag;
    const uint8_t *data = ch->uid;
    if (bit == UPS__OWE_REQUEST) {
        if (!(ch->flags & UPS__PEND)) {
            return 0;
        }
        etag = request_kind(ch);
        ch->t0 = now16(now); /* the request retry counts from here */
    } else if (bit == UPS__OWE_UNSUB) {
        etag = RQ_UNSUB;
    } else if (!(ch->flags & UPS__BOUND)) {
        return 0;
    } else if (bit == UPS__OWE_DECLARE) {
#if UPS_DECLARATIONS
        ups_declaration_t *decl = declaration_of(node, i);
        if (decl == NULL || decl->state <= 0) {
            return 0; /* none, or refused, or given up */
        }
        decl->data[0] = (uint8_t)(etag >> 8); /* the etag it has now */
        decl->data[1] = (uint8_t)etag;
        etag = RQ_DECLARE;
        data = decl->data;
#else
        return 0;
#endif
    } else if (!(ch->flags & (bit >> 1))) { /* SUB_AT: subscribes, PUB_AT: publishes */
        return 0;
    } else {
        priority = bit >> 2; /* PUB_AT at priority 1, SUB_AT at 0 */
    }
    ups__push_request(node, priority, etag, data);
    return 1;
}

int ups__queue_owed(ups_node_t *node, uint32_t now)
{
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        ups_channel_t *ch = &node->channels[i];
        while (ch->owe != 0u) {
            unsigned bit = ch->owe & (0u - (unsigned)ch->owe); /* the lowest: its own order */
            ch->owe = (uint8_t)(ch->owe & ~bit);
            if (queue_one(node, i, bit, now)) {
                return 1;
            }
        }
    }
    return 0;
}

/* ---- Binds --------------------------------------------------------------------------------- */

/** Whether the events of @p etag's size class fit the node's buffers (UPS_MAX_EVENT). */
static int fits(unsigned etag)
{
    return UPS_WITH_TRANSFERS ? ups__class_max(ups__class(etag)) <= UPS_MAX_EVENT
                              : etag < UPS__LARGE_ETAG;
}

/** Rely on @p etag for @p ch from now on (a subscriber's events fit: ups__on_bind saw to it). */
static void adopt(ups_node_t *node, ups_channel_t *ch, uint16_t etag, uint32_t now)
{
    int asked_pub = request_kind(ch) != RQ_SUB_BIND;
    ch->flags = (uint8_t)((ch->flags | UPS__BOUND) & ~(UPS__PEND | UPS__ASKED | UPS__CAND |
                                                       UPS__REBIND | UPS__WAIT));
    ch->etag = etag;
    ch->step = (uint8_t)(ch->step & 0xF0u);
    note(node, UPS_NOTE_CHANNELS);
    if (ch->flags & UPS__SUB) {
        note(node, UPS_NOTE_FILTERS);
    }
    /* the request told the CAN-ECB one role; SUB_AT or PUB_AT tells it the other */
    ch->owe = (uint8_t)(ch->owe | (ch->flags & (asked_pub ? UPS__SUB : UPS__PUB)) << 1);
    if (UPS_WITH_TRANSFERS && (ch->flags & UPS__PUB) && etag >= UPS__LARGE_ETAG) {
        ch->flags = (uint8_t)(ch->flags | UPS__WAIT); /* subscribers re-bind after a move */
        ch->t0 = now16(now);
    }
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
#endif

int ups__etag_known(const ups_node_t *node, uint16_t etag)
{
    int known = 0;
    for (unsigned c = 0; c < UPS_CHANNELS; ++c) {
        known |= node->channels[c].etag == etag;
    }
#if UPS_HEARD_BINDS
    for (unsigned i = 0; i < UPS_HEARD_BINDS; ++i) {
        known |= node->heard_etag[i] == etag;
    }
#endif
    return known;
}

void ups__on_bind(ups_node_t *node, uint16_t etag, const uint8_t *uid, uint32_t now)
{
#if UPS_HEARD_BINDS
    int doubt = heard_other(node, etag, uid);
#else
    int doubt = 0;
#endif
    ups_channel_t *mine = NULL; /* the channel of the Bind's UID */
    int contradiction = 0;
    int grows = 0;     /* the Bind moves one of our channels to a larger size class ... */
    int etag_ours = 0; /* ... and names no etag of ours: a move, not a contradiction */
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        ups_channel_t *ch = &node->channels[i];
        int same_etag = ch->etag == etag;
        int same_uid = ups__same8(ch->uid, uid);
        if (same_uid && (ch->flags | ch->owe) != 0u) {
            mine = ch;
        }
        if ((ch->flags & (UPS__CAND | UPS__BOUND)) && same_etag != same_uid) {
            if (ch->flags & UPS__BOUND) { /* it contradicts a binding relied on */
                grows |= same_uid && ups__class(etag) > ups__class(ch->etag);
                etag_ours |= same_etag;
                contradiction = 1;
                ch->flags = (uint8_t)(ch->flags | UPS__REBIND);
            }
            start_request(node, ch); /* (a spoiled candidate: ask for a fresh answer) */
        }
    }
    if (contradiction) {
        ups__count(grows && !etag_ours ? &node->counters.moves : &node->counters.rebinds);
        return; /* adopt nothing from it */
    }
    unsigned expected = UPS__PEND | UPS__ASKED;
    if (mine == NULL || (mine->flags & (expected | UPS__CAND)) != expected ||
        ups__class(etag) < wanted_class(mine)) {
        return; /* not ours, not asked (yet), settling already, or for a smaller class */
    }
    if (doubt) {
        ups__count(&node->counters.rebinds); /* adopt it when it comes again */
    } else if ((mine->flags & UPS__SUB) && !fits(etag)) {
        ups__refused(node, uid, UPS_ERR_TOO_LARGE, now); /* its events would not fit: a refusal */
    } else if (mine->flags & UPS__REBIND) {
        mine->flags = (uint8_t)(mine->flags | UPS__CAND);
        mine->etag = etag;
        mine->t0 = now16(now);
    } else {
        adopt(node, mine, etag, now);
    }
}

/** The request retry of frame @p owed (the channel's request, or its declaration's DECLARE) on
 *  the channel's timer: owe it again when due; 1 when it is given up. */
static int retry(ups_channel_t *ch, uint32_t now, unsigned owed)
{
    unsigned step = ch->step & 0xFu;
    if ((ch->owe & owed) || ups__since(now, ch->t0) < retry_delay(step)) {
        return 0; /* not sent yet, or not yet due again */
    }
    if (step >= RETRY_STEPS && !(ch->flags & UPS__REBIND)) {
        return 1;
    }
    ch->step = (uint8_t)((ch->step & 0xF0u) | (step < RETRY_STEPS ? step + 1u : step));
    ch->t0 = now16(now);
    ch->owe = (uint8_t)(ch->owe | owed);
    return 0;
}

/** Settling, the publisher's pause, and the retry of the channel's request or, once it is
 *  bound, of its declaration (the channel's timer is free then). */
static void tick_channel(ups_node_t *node, unsigned i, uint32_t now)
{
    ups_channel_t *ch = &node->channels[i];
    unsigned flags = ch->flags;
    uint16_t waited = ups__since(now, ch->t0);
#if UPS_DECLARATIONS
    ups_declaration_t *decl = declaration_of(node, i);
#endif
    if (flags & UPS__CAND) {
        if (waited >= SETTLE) {
            adopt(node, ch, ch->etag, now); /* it stood 50 ms with nothing contradicting it */
        }
    } else if (flags & UPS__PEND) {
        /* a refusal ends the request once it stood 3 s while the node kept asking (a repeat
         * that fell due goes first: after a late tick, the answer to it may void it), or when
         * the request gives up (5 s) with it open */
        int why = refusal_of(ch);
        if (retry(ch, now, UPS__OWE_REQUEST) ||
            (why != 0 && !(ch->owe & UPS__OWE_REQUEST) &&
             (((now >> 2u) - ch->etag) & REFUSAL_TIME) > REFUSAL_WAIT / 4u)) {
            fail(node, ch, why != 0 ? why : UPS_ERR_TIMEOUT);
        }
    } else if (UPS_WITH_TRANSFERS && (flags & UPS__WAIT)) {
        if (waited >= GROW_PAUSE) {
            ch->flags = (uint8_t)(flags & ~UPS__WAIT);
            note(node, UPS_NOTE_CHANNELS);
        }
#if UPS_DECLARATIONS
    } else if ((flags & UPS__BOUND) && decl != NULL && decl->state == UPS_DECL_WAITING) {
        if (decl->heard > HEARD_NONE) { /* no DECLARE after the first verdict: the latest */
            if (waited >= VERDICT_WAIT) { /* stood 0.5 s with no other: the answer */
                follow(node, ch, decl, decl->heard);
            }
        } else if (retry(ch, now, UPS__OWE_DECLARE)) {
            decl->state = UPS_ERR_TIMEOUT;
            note(node, UPS_NOTE_DECLARATIONS);
        }
#endif
    }
}

void ups__tick_bind(ups_node_t *node, uint32_t now)
{
    for (unsigned i = 0; i < UPS_CHANNELS; ++i) {
        tick_channel(node, i, now);
    }
}

/* ---- declarations -------------------------------------------------------------------------- */

#if UPS_DECLARATIONS
void ups__on_verdict(ups_node_t *node, uint16_t etag, int granted, uint8_t priority,
                     uint32_t now)
{
    for (unsigned i = 0; i < UPS_DECLARATIONS; ++i) {
        ups_declaration_t *decl = &node->decl[i];
        if (decl->channel >= UPS_CHANNELS) {
            continue; /* unused */
        }
        ups_channel_t *ch = &node->channels[decl->channel];
        if (!(ch->flags & UPS__BOUND) || ch->etag != etag || decl->state == UPS_ERR_REFUSED ||
            decl->heard == HEARD_UNSENT) {
            continue; /* not a stream it declared (its DECLARE sent, not ended in a Refuse) */
        }
        unsigned verdict = granted ? priority : HEARD_REFUSE;
        if (decl->state != UPS_DECL_WAITING) {
            follow(node, ch, decl, verdict); /* also unasked: another declaration moved it */
        } else {
            decl->heard = (uint8_t)verdict; /* the answer, if it stands 0.5 s (tick_channel) */
            ch->t0 = now16(now);
        }
    }
}
#endif

/* ---- the API ------------------------------------------------------------------------------- */

/** The channel of @p uid with @p role added, or a new one; its index or UPS_ERR_FULL. */
static int add_role(ups_node_t *node, uint64_t uid, unsigned role, unsigned cls)
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
    unsigned had = ch->flags;
    if (role == UPS__SUB) {
        ch->owe = (uint8_t)(ch->owe & ~UPS__OWE_UNSUB); /* back before its UNSUB went */
    }
    if (had == 0u) { /* a new entry, or one whose UNSUB was still owed */
        ch->priority = UPS__DEFAULT_PRIORITY;
        ch->step = 0u;
    }
    ch->flags = (uint8_t)(had | role);
    if (cls > wanted_class(ch)) {
        ch->step = (uint8_t)((ch->step & 0x0Fu) | (cls << 4));
        had &= ~role; /* a larger size class: as a role added */
    }
    if (!(had & UPS__BOUND) ? !(had & role) || !(had & (UPS__PEND | UPS__CAND))
                            : ups__class(ch->etag) < wanted_class(ch)) {
        /* new, failed before, a role (or size class) added while it waits (an answer to the
         * request out would not tell the CAN-ECB), or moving to a larger size class: ask */
        start_request(node, ch);
    } else if (!(had & role)) {
        ch->owe = (uint8_t)(ch->owe | role << 1); /* SUB_AT or PUB_AT: the new role */
        note(node, UPS_NOTE_FILTERS | UPS_NOTE_CHANNELS);
    }
    return i;
}

int ups_subscribe(ups_node_t *node, uint64_t uid, uint32_t now_ms)
{
    (void)now_ms;
    return add_role(node, uid, UPS__SUB, 0u);
}

int ups_advertise(ups_node_t *node, uint64_t uid, uint16_t max_size, uint32_t now_ms)
{
    unsigned cls = 0u;
    (void)now_ms;
    if (max_size > UPS_MAX_EVENT) {
        return UPS_ERR_TOO_LARGE;
    }
    while (UPS_WITH_TRANSFERS && ups__class_max(cls) < max_size) {
        ++cls;
    }
    return add_role(node, uid, UPS__PUB, cls);
}

int ups_unsubscribe(ups_node_t *node, int channel)
{
    if (!ups__valid_channel(node, channel)) {
        return UPS_ERR_ARGUMENT;
    }
    ups_channel_t *ch = &node->channels[channel];
    if (ch->flags & UPS__SUB) {
        ch->flags = (uint8_t)(ch->flags & ~UPS__SUB);
        if (ch->flags & UPS__PEND) {
            start_request(node, ch); /* the request out would not tell the publisher's role */
        }
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

int ups_channel_priority(const ups_node_t *node, int channel)
{
    if (ups_channel_state(node, channel) == UPS_CHANNEL_FREE) { /* not a channel in use */
        return UPS_ERR_ARGUMENT;
    }
    return node->channels[channel].priority;
}

int ups_channel_state(const ups_node_t *node, int channel)
{
    if (!ups__valid_channel(node, channel)) {
        return UPS_CHANNEL_FREE;
    }
    unsigned flags = node->channels[channel].flags;
    if (flags & (UPS__PEND | UPS__CAND | UPS__WAIT)) {
        return UPS_CHANNEL_WAITING;
    }
    if (flags & UPS__BOUND) {
        return UPS_CHANNEL_BOUND;
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
    if (!ups__valid_channel(node, channel)) {
        return UPS_ERR_ARGUMENT;
    }
    ups_channel_t *ch = &node->channels[channel];
    if (!(ch->flags & UPS__PUB) || period == 0u || deadline == 0u ||
        (ch->etag < UPS__LARGE_ETAG ? size > 8u : size == 0u)) {
        return UPS_ERR_ARGUMENT;
    }
    if ((ch->flags & (UPS__BOUND | UPS__WAIT)) != UPS__BOUND) {
        return UPS_ERR_UNBOUND; /* not in state 2 */
    }
    ups_declaration_t *decl = declaration_of(node, (unsigned)channel);
    if (decl == NULL && (decl = declaration_of(node, 0xFFu)) == NULL) {
        return UPS_ERR_FULL;
    }
    if (decl->channel != channel || decl->state <= 0) {
        decl->fallback = ch->priority; /* (not a granted one: declared again) */
    }
    decl->channel = (uint8_t)channel;
    decl->state = UPS_DECL_WAITING;
    decl->heard = HEARD_UNSENT;
    decl->data[2] = size;
    decl->data[3] = (uint8_t)(period >> 8);
    decl->data[4] = (uint8_t)period;
    decl->data[5] = (uint8_t)(deadline >> 8);
    decl->data[6] = (uint8_t)deadline;
    decl->data[7] = jitter;
    ch->step = (uint8_t)(ch->step & 0xF0u); /* the channel's retry timer, free while bound */
    ch->t0 = now16(now_ms);
    ch->owe = (uint8_t)(ch->owe | UPS__OWE_DECLARE);
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
