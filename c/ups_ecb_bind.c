/*
 * libups-ecb: etags by UID (size classes, the contradiction rule, EtagsFull, Limit, the quota,
 * leases), who uses which channel (SUB_BIND, PUB_BIND, UNSUB, SUB_AT, PUB_AT), requests held
 * in the recovery window, the Roster's answers, and declared streams (DECLARE, Grant, Refuse,
 * by ups_ecb_rt.c). As broker/_etags.py, _channels.py, _quota.py, _roster.py, _forged.py and
 * _admission.py do (docs/protocol.md, "Binding", "Events larger than one frame", "Restarts",
 * "The roster", "Real-time channels", "Bounds").
 *
 * A binding is stored when its Bind is queued: the application saves the blob on
 * UPS_ECB_NOTE_STATE before it sends the frames queued since, so nothing is announced that a
 * reset would forget. Users and creators are node entries (ups_ecb_join_t.nodes); frames name
 * their TxNodes.
 */
#include "ups_ecb_internal.h"

/* the etag field of a node's request (docs/protocol.md, "Management frames") */
#define PUB_BIND 1u
#define SUB_BIND 2u
#define UNSUB 3u
#define DECLARE 5u
#define ROSTER 6u
#define PUB_BIND_CLASS 8u /* + c: PUB_BIND(c), c = 1..4 */

/* the CAN-ECB's frames (TxNode 0x7F, priority 0): the etag field */
#define F_ETAGS_FULL 0x3200u
#define F_GRANT 0x3400u
#define F_REFUSE 0x3500u
#define F_LIMIT 0x3800u
#define F_USES_SUB 0x3A00u /* + 0x100: Uses(pub), + 0x200: RosterEnd */
#define F_ROSTER_END 0x3C00u
#define BIND_PRIORITY 1u

/* what the answer to a Roster lists next (r_role) */
#define R_SUBS 0u  /* the subscribers of channel r_uid */
#define R_PUBS 1u  /* its publishers */
#define R_NEXT 2u  /* the channel after r_uid */
#define R_FIRST 3u /* the channel at r_uid or after (the cursor) */

#define ANY 0xFFu     /* oldest_idle: of any size class */
#define NONE 0xFFu    /* roster: no TxNode */
#define AGE_PAST 17u  /* ages are sixteenths of the lease, rounded up: 17 is past it for sure */
#define DECLARE_BURST 20u
#define DECLARE_GAP 100u /* ms per DECLARE token: 10 a second */
#define ROSTER_PAGE 32u
#define ROSTER_BURST 48u
#define ROSTER_GAP 5u    /* ms per roster frame: 200 a second */
#define ROOM 2u          /* TX queue places paced answers (rosters, held requests) leave free */
#define UNBOUNDED 0xFFFFu

/* ---- small helpers --------------------------------------------------------------------------- */

static unsigned size_class(unsigned etag)
{
    return etag < UPS_ECB__LARGE_ETAG ? 0u : 1u + ((etag - UPS_ECB__LARGE_ETAG) >> 10);
}

static unsigned has(const uint8_t *map, unsigned slot)
{
    return ((unsigned)map[slot >> 3] >> (slot & 7u)) & 1u;
}

/** Set (@p on) or clear node entry @p slot in @p map; a change is a change of the users. */
static void mark(ups_ecb_t *ecb, uint8_t *map, unsigned slot, unsigned on)
{
    unsigned old = map[slot >> 3];
    unsigned bit = 1u << (slot & 7u);
    unsigned now = on ? old | bit : old & ~bit;
    if (now != old) {
        map[slot >> 3] = (uint8_t)now;
        ups_ecb__note(ecb, UPS_ECB_NOTE_CHANNELS);
    }
}

static unsigned uses(const ups_ecb_channel_t *ch, unsigned slot)
{
    return has(ch->use[0], slot) | has(ch->use[1], slot);
}

static int in_use(const ups_ecb_channel_t *ch)
{
    unsigned any = 0u;
    for (unsigned k = 0u; k < UPS_ECB_NODE_BYTES; k++) {
        any |= (unsigned)(ch->use[0][k] | ch->use[1][k]);
    }
    return any != 0u;
}

static unsigned get16(const uint8_t *in)
{
    return ((unsigned)in[0] << 8) | in[1];
}

static void put16(uint8_t *out, unsigned value)
{
    out[0] = (uint8_t)(value >> 8);
    out[1] = (uint8_t)value;
}

/* a struct copy through ups_ecb__copy, so that no compiler makes a memcpy call of it (no C
 * library) */
static void copy_stream(ups_ecb_stream_t *to, const ups_ecb_stream_t *from)
{
    ups_ecb__copy((uint8_t *)to, (const uint8_t *)from, (unsigned)sizeof(*to));
}

/** -1, 0, 1 as UID @p a is below, equal to or above @p b. */
static int uid_cmp(const uint8_t *a, const uint8_t *b)
{
    for (unsigned k = 0u; k < 8u; k++) {
        if (a[k] != b[k]) {
            return a[k] < b[k] ? -1 : 1;
        }
    }
    return 0;
}

/* the channel entries by UID or etag (0: a free entry); NULL when none */
static ups_ecb_channel_t *find_uid(ups_ecb_t *ecb, const uint8_t *uid)
{
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag != 0u && ups_ecb__same8(ch->uid, uid)) {
            return ch;
        }
    }
    return NULL;
}

static ups_ecb_channel_t *find_etag(ups_ecb_t *ecb, unsigned etag)
{
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag == etag) {
            return ch;
        }
    }
    return NULL;
}

/** Queue a CAN-ECB frame (TxNode 0x7F) of 8 bytes: @p data, zeros when NULL. */
static void send_mgmt(ups_ecb_t *ecb, unsigned priority, unsigned field, const uint8_t *data)
{
    ups_ecb__send(ecb, ups_ecb__id(priority, UPS_ECB__MGMT, field), data, 8u);
}

static void send_bind(ups_ecb_t *ecb, unsigned etag, const uint8_t *uid)
{
    send_mgmt(ecb, BIND_PRIORITY, etag, uid);
}

/** Whether the answers paced by the tick (held requests, rosters) may go now: the CAN-ECB
 *  answers the bus (a candidate or serving, not standing by, not in a recovery window) and the
 *  TX queue has room. */
static int may_answer(const ups_ecb_t *ecb)
{
    unsigned role = ecb->elect.role;
    return !ecb->recovering && (role == UPS_ECB_CANDIDATE || role == UPS_ECB_SERVING) &&
           ecb->tx_count + ROOM < UPS_ECB_TX_DEPTH;
}

/* ---- leases ---------------------------------------------------------------------------------- */

/** Milliseconds of one age step: a sixteenth of the lease, rounded up (lease_s is 1 to
 *  LEASE_MAX_S, 10^6, as ups_ecb_init checks: no overflow, and a step is 63 ms at least). */
static uint32_t age_unit(const ups_ecb_t *ecb)
{
    return (ecb->cfg.lease_s * 1000u + 15u) / 16u;
}

/** The channel unused longest, past the lease, that no node uses: of size class @p c (or ANY),
 *  created by node entry @p creator - 1 (or by anyone: 0); NULL when there is none. */
static ups_ecb_channel_t *oldest_idle(ups_ecb_t *ecb, unsigned c, unsigned creator)
{
    ups_ecb_channel_t *best = NULL;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag != 0u && !in_use(ch) && ch->age >= AGE_PAST &&
            (c == ANY || size_class(ch->etag) == c) && (creator == 0u || ch->creator == creator) &&
            (best == NULL || ch->age > best->age)) {
            best = ch;
        }
    }
    return best;
}

static void drop_streams(ups_ecb_t *ecb, unsigned etag, unsigned txnode);

/** Unbind channel @p ch, unused past the lease: its etag is free, its creator's quota too. */
static void reclaim(ups_ecb_t *ecb, ups_ecb_channel_t *ch)
{
    drop_streams(ecb, ch->etag, NONE);
    ups_ecb__copy((uint8_t *)ch, NULL, (unsigned)sizeof(*ch));
    ups_ecb__count(&ecb->counters.reclaimed);
    ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
}

/** The lowest free etag of size class @p c, else the one unused longest past the lease
 *  (reclaimed); 0 when none. */
static unsigned free_etag(ups_ecb_t *ecb, unsigned c)
{
    unsigned end = UPS_ECB__LARGE_ETAG + (c << 10);
    unsigned etag = c == 0u ? UPS_ECB__FIRST_ETAG : end - 0x400u;
    /* past every etag taken, until a pass over the table finds the candidate free: at most
     * UPS_ECB_CHANNELS + 1 passes (each but the last moves past an entry's etag), mostly two
     * (the entries are mostly in etag order) */
    for (int moved = 1; moved && etag < end;) {
        moved = 0;
        for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
            if (ecb->bind.channels[i].etag == etag) {
                etag++;
                moved = 1;
            }
        }
    }
    if (etag < end) {
        return etag;
    }
    ups_ecb_channel_t *old = oldest_idle(ecb, c, 0u);
    if (old == NULL) {
        return 0u;
    }
    etag = old->etag;
    reclaim(ecb, old);
    return etag;
}

static void age_channels(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    uint32_t unit = age_unit(ecb);
    unsigned steps = 0u;
    while (ups_ecb__since(ecb->now, b->t_aged) >= unit) {
        b->t_aged += unit;
        if (++steps > AGE_PAST) {
            b->t_aged = ecb->now;
        }
    }
    for (unsigned i = 0u; steps > 0u && i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &b->channels[i];
        unsigned age = ch->age + steps;
        ch->age = (uint8_t)(age < 0xFFu ? age : 0xFFu);
    }
}

/* ---- declared streams ------------------------------------------------------------------------ */

/** A stream's place in the order the analysis takes them: (etag, TxNode). */
static unsigned stream_key(const ups_ecb_stream_t *s)
{
    return ((unsigned)s->etag << 7) | s->txnode;
}

static ups_ecb_stream_t *find_stream(ups_ecb_t *ecb, unsigned etag, unsigned txnode)
{
    for (unsigned k = 0u; k < ecb->bind.stream_count; k++) {
        ups_ecb_stream_t *s = &ecb->bind.streams[k];
        if (s->etag == etag && s->txnode == txnode) {
            return s;
        }
    }
    return NULL;
}

/* A stream as the blob has it (STREAM bytes): ups_ecb_stream_t's fields in order (etag, TxNode,
 * size, period, deadline, jitter, priority), the 16-bit ones big-endian. */
#define STREAM 10u
typedef char stream_record_check[sizeof(ups_ecb_stream_t) == STREAM &&
                                         offsetof(ups_ecb_stream_t, period) == 4u &&
                                         offsetof(ups_ecb_stream_t, priority) == 9u
                                     ? 1
                                     : -1];

static void load_stream(ups_ecb_stream_t *s, const uint8_t *in)
{
    ups_ecb__copy((uint8_t *)s, in, STREAM);
    s->etag = (uint16_t)get16(in);
    s->period = (uint16_t)get16(in + 4);
    s->deadline = (uint16_t)get16(in + 6);
}

static void store_stream(uint8_t *out, const ups_ecb_stream_t *s)
{
    ups_ecb__copy(out, (const uint8_t *)s, STREAM);
    put16(out, s->etag);
    put16(out + 4, s->period);
    put16(out + 6, s->deadline);
}

/** Drop the streams on @p etag (the channel left it: moved or reclaimed), or when @p etag is 0,
 *  those of TxNode @p txnode and of TxNodes nobody holds; and the Refuse remembered of them. */
static void drop_streams(ups_ecb_t *ecb, unsigned etag, unsigned txnode)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (unsigned k = b->stream_count; k-- > 0u;) {
        ups_ecb_stream_t *s = &b->streams[k];
        if (etag != 0u ? s->etag == etag
                       : s->txnode == txnode || ups_ecb__holder(ecb, s->txnode) < 0) {
            b->stream_count--;
            ups_ecb__copy((uint8_t *)s, (const uint8_t *)(s + 1),
                          (b->stream_count - k) * (unsigned)sizeof(*s));
            b->refused_valid = 0u;
            ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        }
    }
    unsigned refused = get16(b->refuse);
    if (refused != 0u && (etag != 0u ? refused == etag : b->refuse[2] == txnode)) {
        ups_ecb__copy(b->refuse, NULL, 8u);
        b->refused_valid = 0u;
    }
}

static void send_grant(ups_ecb_t *ecb, const ups_ecb_stream_t *s)
{
    uint8_t data[8];
    ups_ecb__copy(data, NULL, 8u);
    put16(data, s->etag);
    data[2] = s->txnode;
    data[3] = s->priority;
    send_mgmt(ecb, 0u, F_GRANT, data);
}

/** DECLARE: the admitted streams and the new one analysed: Grants, or a Refuse. */
static void declare(ups_ecb_t *ecb, unsigned slot, unsigned txnode, const uint8_t *data)
{
    ups_ecb_bind_t *b = &ecb->bind;
    uint8_t in[10]; /* the DECLARE as the blob has a stream: its TxNode after the etag */
    in[0] = data[0];
    in[1] = data[1];
    in[2] = (uint8_t)txnode;
    ups_ecb__copy(in + 3, data + 2, 6u);
    in[9] = 0u;
    ups_ecb_stream_t s;
    load_stream(&s, in);
    const ups_ecb_channel_t *ch = find_etag(ecb, s.etag); /* the fields are in range (the
                                                                dispatcher checked them) */
    if (ch == NULL || !has(ch->use[1], slot)) {
        ups_ecb__count(&ecb->counters.malformed); /* as the Python CAN-ECB counts it */
        return;
    }
    const ups_ecb_stream_t *again = find_stream(ecb, s.etag, txnode);
    if (again != NULL && ups_ecb__same8((const uint8_t *)again, (const uint8_t *)&s) &&
        again->jitter == s.jitter) {
        send_grant(ecb, again); /* asked again: the same answer, no analysis */
        return;
    }
    if (b->refused_valid && b->refuse[2] == txnode && ups_ecb__same8(b->refused_decl, data)) {
        send_mgmt(ecb, 0u, F_REFUSE, b->refuse);
        return;
    }
    if (b->spent[slot] >= DECLARE_BURST) {
        ups_ecb__count(&ecb->counters.limited);
        return;
    }
    b->spent[slot]++;
    /* the streams with the new one in its place by (etag, TxNode): declared again, replaced */
    ups_ecb_stream_t work[UPS_ECB_STREAMS + 1];
    unsigned count = b->stream_count;
    ups_ecb__copy((uint8_t *)work, (const uint8_t *)b->streams, count * (unsigned)sizeof(s));
    unsigned at = again != NULL ? (unsigned)(again - b->streams) : 0u;
    if (again == NULL) {
        for (at = count++; at > 0u && stream_key(&work[at - 1u]) > stream_key(&s); at--) {
            copy_stream(&work[at], &work[at - 1u]);
        }
    }
    copy_stream(&work[at], &s);
    unsigned miss = 0u;
    uint16_t response = 0u;
    if (count > (unsigned)UPS_ECB_STREAMS) {
        ups_ecb__count(&ecb->counters.streams_full);
    } else if (ups_ecb_rt_admit(work, count, ecb->cfg.bitrate, ecb->cfg.fd, &miss, &response)) {
        /* a Grant for the stream and for every stream whose priority moves: all of them are
         * queued, or none and nothing changes (a node never hears its new priority otherwise);
         * the node asks again (docs/protocol.md, Bounds) */
        unsigned grants = 0u;
        for (int pass = 0; pass < 2; pass++) {
            for (unsigned j = 0u; j < count; j++) {
                const ups_ecb_stream_t *old = find_stream(ecb, work[j].etag, work[j].txnode);
                if (j == at || old == NULL || old->priority != work[j].priority) {
                    if (pass == 0) {
                        grants++;
                    } else {
                        send_grant(ecb, &work[j]);
                    }
                }
            }
            if (pass == 0 && grants > UPS_ECB_TX_DEPTH - (unsigned)ecb->tx_count) {
                ups_ecb__count(&ecb->counters.tx_dropped);
                return;
            }
        }
        ups_ecb__copy((uint8_t *)b->streams, (const uint8_t *)work, count * (unsigned)sizeof(s));
        b->stream_count = (uint8_t)count;
        b->refused_valid = 0u;
        if (get16(b->refuse) == s.etag && b->refuse[2] == txnode) {
            ups_ecb__copy(b->refuse, NULL, 8u);
        }
        ups_ecb__count(&ecb->counters.admitted);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        return;
    } else if (miss >= count) { /* more streams than priorities */
        response = 0u;
    }
    /* Refused, naming the stream that would miss, and remembered (the answer to the same
     * DECLARE again, and to a forged Grant of the stream) */
    const ups_ecb_stream_t *m = response == 0u ? &s : &work[miss];
    uint8_t *r = b->refuse;
    ups_ecb__copy(r, in, 3u); /* the stream: etag, TxNode */
    r[3] = m->txnode;
    put16(r + 4, m->etag);
    put16(r + 6, response);
    ups_ecb__copy(b->refused_decl, data, 8u);
    b->refused_valid = 1u;
    ups_ecb__count(&ecb->counters.refused);
    send_mgmt(ecb, 0u, F_REFUSE, r);
}

/* ---- binding --------------------------------------------------------------------------------- */

/** May node entry @p slot (TxNode @p txnode) use the channel of @p uid (@p known, or NULL), and
 *  when it creates it (@p c: its size class; else > 4), is it within its quota? Past its quota,
 *  the one it created that was unused longest is reclaimed, once past the lease. If not, Limit,
 *  counted. */
static int allowed(ups_ecb_t *ecb, unsigned slot, unsigned txnode,
                   const ups_ecb_channel_t *known, const uint8_t *uid, unsigned c)
{
    unsigned used = 0u;
    unsigned made = 0u;
    for (unsigned j = 0u; j < UPS_ECB_CHANNELS; j++) { /* an unused entry: no user, nobody's */
        const ups_ecb_channel_t *ch = &ecb->bind.channels[j];
        used += uses(ch, slot);
        made += ch->creator == slot + 1u && size_class(ch->etag) == c;
    }
    UPS_ECB_COUNTER_T *counter = &ecb->counters.limited;
    if (known != NULL && uses(known, slot)) {
        used = 0u; /* it uses it already */
    }
    if (used < ecb->cfg.max_channels) {
        if (c > 4u || made < ecb->cfg.quota[c]) {
            return 1;
        }
        ups_ecb_channel_t *old = oldest_idle(ecb, c, slot + 1u);
        if (old != NULL) {
            reclaim(ecb, old);
            return 1;
        }
        counter = &ecb->counters.quota_hit;
    }
    ups_ecb__count(counter);
    send_mgmt(ecb, 0u, F_LIMIT | txnode, uid);
    return 0;
}

/** A free entry of the table, reclaiming the channel unused longest past the lease if need be;
 *  NULL when none (counted: channels_full). */
static ups_ecb_channel_t *free_entry(ups_ecb_t *ecb)
{
    ups_ecb_channel_t *ch = find_etag(ecb, 0u);
    if (ch == NULL) {
        ch = oldest_idle(ecb, ANY, 0u);
        if (ch == NULL) {
            ups_ecb__count(&ecb->counters.channels_full);
        } else {
            reclaim(ecb, ch);
        }
    }
    return ch;
}

static void hold(ups_ecb_t *ecb, unsigned txnode, unsigned kind, const uint8_t *uid)
{
    for (unsigned h = 0u; h < UPS_ECB_HELD; h++) {
        ups_ecb_held_t *held = &ecb->bind.held[h];
        if (held->kind == 0u) {
            ups_ecb__copy(held->uid, uid, 8u);
            held->txnode = (uint8_t)txnode;
            held->kind = (uint8_t)kind;
        } else if (held->kind != kind || held->txnode != txnode ||
                   !ups_ecb__same8(held->uid, uid)) {
            continue;
        }
        ups_ecb__count(&ecb->counters.deferred);
        return;
    }
    ups_ecb__count(&ecb->counters.held_dropped);
}

/** Drop the @p h-th held request: the later ones move up (the held requests are the first
 *  entries, oldest first). */
static void unhold(ups_ecb_bind_t *b, unsigned h)
{
    ups_ecb__copy((uint8_t *)&b->held[h], (const uint8_t *)&b->held[h + 1u],
                  (UPS_ECB_HELD - 1u - h) * (unsigned)sizeof(b->held[0]));
    b->held[UPS_ECB_HELD - 1u].kind = 0u;
}

/** The tables' Binds of @p etag and of @p uid where they differ from (etag, uid), a conflict
 *  (none when the tables bind them to each other). */
static void correct(ups_ecb_t *ecb, unsigned etag, const uint8_t *uid)
{
    const ups_ecb_channel_t *of_etag = find_etag(ecb, etag);
    const ups_ecb_channel_t *of_uid = find_uid(ecb, uid);
    if (of_uid == of_etag) { /* bound to each other, or both unknown */
        return;
    }
    ups_ecb__count(&ecb->counters.conflicts);
    if (of_etag != NULL) {
        send_bind(ecb, etag, of_etag->uid);
    }
    if (of_uid != NULL) { /* etags are unique: its etag is not @p etag */
        send_bind(ecb, of_uid->etag, uid);
    }
}

/** Node entry @p slot (TxNode @p txnode) uses the channel of @p uid: it asks for it (@p etag 0;
 *  @p kind the request's etag field: SUB_BIND, PUB_BIND or PUB_BIND(c)), or it holds it bound
 *  to @p etag (SUB_AT, PUB_AT: @p kind SUB_BIND or PUB_BIND), which is adopted when the tables
 *  have neither. */
static void bind(ups_ecb_t *ecb, unsigned slot, unsigned txnode, unsigned kind,
                 const uint8_t *uid, unsigned etag)
{
    unsigned c = etag != 0u ? size_class(etag) : kind > PUB_BIND_CLASS ? kind - PUB_BIND_CLASS : 0u;
    ups_ecb_channel_t *ch = find_uid(ecb, uid);
    int fits = ch != NULL && (etag != 0u ? ch->etag == etag : size_class(ch->etag) >= c);
    if (etag != 0u && !fits && (ch != NULL || find_etag(ecb, etag) != NULL)) { /* contradicted */
        correct(ecb, etag, uid);
        if (ch != NULL || ecb->recovering) {
            return;
        }
        etag = 0u; /* it will ask again: answered now, as its request (of size class 0) */
        c = 0u;
    }
    if (etag == 0u && ecb->recovering && !fits) {
        hold(ecb, txnode, kind, uid);
        return;
    }
    if (!allowed(ecb, slot, txnode, ch, uid, fits ? 5u : c)) {
        return;
    }
    if (!fits) {
        unsigned to = etag;
        if (ch == NULL) { /* a new channel: an entry first (one reclaimed frees its etag too) */
            ch = free_entry(ecb);
            if (ch == NULL && etag != 0u) {
                return;
            }
        }
        if (to == 0u && ch != NULL) {
            to = free_etag(ecb, c);
        }
        if (to == 0u) {
            ups_ecb__count(&ecb->counters.refused);
            send_mgmt(ecb, 0u, F_ETAGS_FULL, uid);
            return;
        }
        if (ch->etag != 0u) { /* a move to a larger size class */
            ups_ecb__count(&ecb->counters.moved);
            drop_streams(ecb, ch->etag, NONE);
        }
        ups_ecb__copy(ch->uid, uid, 8u);
        ch->etag = (uint16_t)to;
        ch->creator = (uint8_t)(slot + 1u);
        ch->age = 0u;
        ups_ecb__count(etag != 0u ? &ecb->counters.adopted : &ecb->counters.bound);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    }
    mark(ecb, ch->use[kind != SUB_BIND], slot, 1u);
    if (etag == 0u) {
        ch->age = 0u; /* just answered: not unused (no reclaim takes it now) */
        send_bind(ecb, ch->etag, uid);
    }
}

static void unsubscribe(ups_ecb_t *ecb, unsigned slot, unsigned txnode, const uint8_t *uid)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (unsigned h = 0u; h < UPS_ECB_HELD; h++) { /* a SUB_BIND held (once at most): dropped */
        const ups_ecb_held_t *held = &b->held[h];
        if (held->kind == SUB_BIND && held->txnode == txnode && ups_ecb__same8(held->uid, uid)) {
            unhold(b, h);
            break;
        }
    }
    ups_ecb_channel_t *ch = find_uid(ecb, uid);
    if (ch != NULL) {
        mark(ecb, ch->use[0], slot, 0u);
    }
}

/* ---- the roster ------------------------------------------------------------------------------ */

/** The channel in use (so bound) with the lowest UID at or (@p after) above @p uid; NULL when
 *  none. */
static const ups_ecb_channel_t *next_channel(const ups_ecb_t *ecb, const uint8_t *uid, int after)
{
    const ups_ecb_channel_t *best = NULL;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (in_use(ch) && uid_cmp(ch->uid, uid) >= after &&
            (best == NULL || uid_cmp(ch->uid, best->uid) < 0)) {
            best = ch;
        }
    }
    return best;
}

/** The lowest TxNode from @p from on of the node entries in @p map; NONE when none. */
static unsigned next_user(const ups_ecb_t *ecb, const uint8_t *map, unsigned from)
{
    unsigned best = NONE;
    for (unsigned j = 0u; j < UPS_ECB_NODES; j++) {
        unsigned t = ecb->join.nodes[j].txnode; /* 0xFF (NONE) in an unused entry */
        if (has(map, j) && t >= from && t < best) {
            best = t;
        }
    }
    return best;
}

/** Send the answer's next frame: a Uses of the channel r_uid, else the RosterEnd of the page
 *  when the next channel starts none or there is none. */
static void roster_step(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (;;) {
        const ups_ecb_channel_t *ch;
        if (b->r_role <= R_PUBS) {
            ch = find_uid(ecb, b->r_uid);
            if (ch != NULL) {
                unsigned t = next_user(ecb, ch->use[b->r_role], b->r_from);
                if (t != NONE) {
                    send_mgmt(ecb, 0u, (F_USES_SUB + ((unsigned)b->r_role << 8)) | t, ch->uid);
                    b->r_from = (uint8_t)(t + 1u);
                    b->r_count++;
                    return;
                }
            }
            b->r_role = (uint8_t)(ch != NULL ? b->r_role + 1u : R_NEXT); /* gone: the next */
            b->r_from = 0u;
            continue;
        }
        ch = next_channel(ecb, b->r_uid, b->r_role == R_NEXT);
        if (ch == NULL || b->r_count >= ROSTER_PAGE) {
            unsigned done = ch == NULL;
            send_mgmt(ecb, 0u, F_ROSTER_END | (done << 7) | b->r_asker, done ? NULL : ch->uid);
            b->r_active = 0u;
            return;
        }
        ups_ecb__copy(b->r_uid, ch->uid, 8u);
        b->r_role = R_SUBS;
    }
}

/** Drop the Roster of node entry @p slot that waits; whether one did. */
static int roster_unqueue(ups_ecb_bind_t *b, unsigned slot)
{
    unsigned to = 0u;
    for (unsigned q = 0u; q < b->r_waiting; q++) {
        if (b->rosters[q].slot != slot) {
            ups_ecb__copy((uint8_t *)&b->rosters[to++], (const uint8_t *)&b->rosters[q],
                          (unsigned)sizeof b->rosters[q]);
        }
    }
    int dropped = to != b->r_waiting;
    b->r_waiting = (uint8_t)to;
    return dropped;
}

/** Whether a roster frame (Uses, RosterEnd) waits in the TX queue: the queue sends the lowest
 *  identifier first, so the answer's frames go one at a time to keep their order. */
static int roster_queued(const ups_ecb_t *ecb)
{
    for (unsigned q = 0u; q < ecb->tx_count; q++) {
        if (ecb->tx[q].id - ups_ecb__id(0u, UPS_ECB__MGMT, F_USES_SUB) < 0x300u) {
            return 1;
        }
    }
    return 0;
}

static void roster_pump(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    while (b->r_tokens > 0u && may_answer(ecb) && !roster_queued(ecb)) {
        if (!b->r_active) {
            if (b->r_waiting == 0u) {
                return;
            }
            unsigned slot = b->rosters[0].slot;
            ups_ecb__copy(b->r_uid, b->rosters[0].cursor, 8u);
            (void)roster_unqueue(b, slot);
            b->r_asker = ecb->join.nodes[slot].txnode;
            if (b->r_asker == 0xFFu) {
                continue;
            }
            b->r_role = R_FIRST;
            b->r_count = 0u;
            b->r_active = 1u;
        }
        roster_step(ecb);
        b->r_tokens--;
        ups_ecb__count(&ecb->counters.roster_frames);
    }
}

/* ---- the part's entries ---------------------------------------------------------------------- */

void ups_ecb__bind_init(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    ups_ecb__copy((uint8_t *)b->channels, NULL, (unsigned)sizeof b->channels);
    b->stream_count = 0u;
    b->r_tokens = ROSTER_BURST;
}

/* The dispatcher (ups_ecb.c, kind_of) let through only well-formed requests: SUB_AT and PUB_AT
 * at priority 0 or 1, the others at priority 0, 8 bytes each, a DECLARE's fields in range. */
void ups_ecb__bind_request(ups_ecb_t *ecb, int slot, uint32_t id, const uint8_t *data)
{
    unsigned priority = (unsigned)(id >> UPS_ECB__PRIO_SHIFT);
    unsigned txnode = (unsigned)(id >> UPS_ECB__TXNODE_SHIFT) & UPS_ECB__MGMT;
    unsigned field = (unsigned)id & UPS_ECB__ETAG_MASK;
    unsigned s = (unsigned)slot;
    if (field == UNSUB) {
        unsubscribe(ecb, s, txnode, data);
    } else if (field == DECLARE) {
        declare(ecb, s, txnode, data);
    } else if (field == ROSTER) {
        ups_ecb_bind_t *b = &ecb->bind;
        ups_ecb__count(&ecb->counters.rosters);
        if (roster_unqueue(b, s)) { /* a newer one replaces the one waiting, at the back */
            ups_ecb__count(&ecb->counters.roster_replaced);
        } else if (b->r_waiting >= UPS_ECB_ROSTERS) { /* not kept: the node asks again */
            ups_ecb__count(&ecb->counters.rosters_full);
            return;
        }
        ups_ecb_roster_t *r = &b->rosters[b->r_waiting++];
        r->slot = (uint8_t)s;
        ups_ecb__copy(r->cursor, data, 8u);
        roster_pump(ecb);
    } else if (field < UPS_ECB__FIRST_ETAG) { /* PUB_BIND, SUB_BIND, PUB_BIND(c) */
        bind(ecb, s, txnode, field, data, 0u);
    } else { /* SUB_AT, PUB_AT (priority 1) of the etag in the field */
        bind(ecb, s, txnode, priority == BIND_PRIORITY ? PUB_BIND : SUB_BIND, data, field);
    }
}

void ups_ecb__bind_event(ups_ecb_t *ecb, unsigned etag)
{
    ups_ecb_channel_t *ch = find_etag(ecb, etag); /* an event's etag: not 0 */
    if (ch != NULL) {
        ch->age = 0u;
    }
}

static void forget_slot(ups_ecb_t *ecb, int slot, int creations)
{
    ups_ecb_bind_t *b = &ecb->bind;
    unsigned s = (unsigned)slot;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &b->channels[i];
        mark(ecb, ch->use[0], s, 0u);
        mark(ecb, ch->use[1], s, 0u);
        if (creations && ch->creator == s + 1u) {
            ch->creator = 0u;
            ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        }
    }
    drop_streams(ecb, 0u, ecb->join.nodes[s].txnode);
    (void)roster_unqueue(b, s);
    b->spent[s] = 0u;
}

void ups_ecb__bind_forget(ups_ecb_t *ecb, int slot)
{
    forget_slot(ecb, slot, 1);
}

void ups_ecb__bind_rejoined(ups_ecb_t *ecb, int slot)
{
    forget_slot(ecb, slot, 0);
}

void ups_ecb__bind_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    unsigned priority = (unsigned)(id >> UPS_ECB__PRIO_SHIFT);
    unsigned field = (unsigned)id & UPS_ECB__ETAG_MASK;
    (void)len; /* 8: Bind, Grant and Refuse have 8 bytes (the dispatcher checked them) */
    if (priority != 0u) { /* a Bind: the CAN-ECB's other frames are at priority 0 */
        correct(ecb, field, data);
        return;
    }
    if (field != F_GRANT && field != F_REFUSE) {
        return;
    }
    unsigned etag = get16(data);
    unsigned txnode = data[2];
    const ups_ecb_stream_t *s = find_stream(ecb, etag, txnode);
    const uint8_t *r = ecb->bind.refuse;
    uint8_t own[8]; /* naming the stream itself, unbounded */
    if (s != NULL) {
        if (field == F_GRANT && data[3] == s->priority) {
            return;
        }
        send_grant(ecb, s);
    } else if (field == F_GRANT) { /* a stream it has not admitted */
        ups_ecb__copy(own, data, 3u);
        own[3] = data[2];
        put16(own + 4, etag);
        put16(own + 6, UNBOUNDED);
        send_mgmt(ecb, 0u, F_REFUSE, get16(r) == etag && r[2] == txnode ? r : own);
    } else {
        return;
    }
    ups_ecb__count(&ecb->counters.conflicts);
}

/** Answer the requests held in the recovery window, oldest first, as far as the TX queue has
 *  room (each answer is one frame); the rest at the next ticks. */
static void replay(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (unsigned done = 0u; b->held[0].kind != 0u && may_answer(ecb); done++) {
        const ups_ecb_held_t *held = &b->held[0];
        const ups_ecb_channel_t *ch = find_uid(ecb, held->uid);
        if (done > 0u && ch != NULL && held->kind > PUB_BIND_CLASS &&
            size_class(ch->etag) < held->kind - PUB_BIND_CLASS) {
            break; /* a move: in a call of its own, so that no Bind this call sent is stale
                      in the blob saved after it */
        }
        int slot = ups_ecb__holder(ecb, held->txnode);
        if (slot >= 0) { /* not in a recovery window: bind() holds nothing */
            bind(ecb, (unsigned)slot, held->txnode, held->kind, held->uid, 0u);
        }
        unhold(b, 0u);
    }
}

void ups_ecb__bind_recovered(ups_ecb_t *ecb)
{
    replay(ecb); /* the rosters asked meanwhile: at the tick's end (ups_ecb__bind_tick), once
                    the join's part of the tick has reclaimed what it reclaims */
}

void ups_ecb__bind_stop(ups_ecb_t *ecb)
{
    ecb->bind.r_active = 0u;
    ecb->bind.r_waiting = 0u;
}

void ups_ecb__bind_tick(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (!b->timed) {
        b->timed = 1u;
        b->t_aged = b->t_decl = b->t_roster = ecb->now;
    }
    age_channels(ecb);
    for (unsigned n = 0u; ups_ecb__since(ecb->now, b->t_decl) >= DECLARE_GAP; n++) {
        b->t_decl += DECLARE_GAP;
        if (n >= DECLARE_BURST) {
            b->t_decl = ecb->now;
        }
        for (unsigned j = 0u; j < UPS_ECB_NODES; j++) {
            if (b->spent[j] > 0u) {
                b->spent[j]--;
            }
        }
    }
    while (ups_ecb__since(ecb->now, b->t_roster) >= ROSTER_GAP) {
        if (b->r_tokens >= ROSTER_BURST) {
            b->t_roster = ecb->now;
            break;
        }
        b->r_tokens++;
        b->t_roster += ROSTER_GAP;
    }
    replay(ecb);
    roster_pump(ecb);
}

/* ---- the blob's section ---------------------------------------------------------------------- */

#define HEAD 3u     /* channels (u16), streams (u8) */
#define CHANNEL 11u /* uid, etag, the creator's TxNode (0xFF: nobody) */

size_t ups_ecb__bind_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    const ups_ecb_bind_t *b = &ecb->bind;
    unsigned channels = 0u;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        channels += b->channels[i].etag != 0u;
    }
    size_t size = HEAD + CHANNEL * (size_t)channels + STREAM * (size_t)b->stream_count;
    if (cap < size) {
        return 0u;
    }
    put16(out, channels);
    out[2] = b->stream_count;
    uint8_t *at = out + HEAD;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &b->channels[i];
        if (ch->etag != 0u) {
            ups_ecb__copy(at, ch->uid, 8u);
            put16(at + 8, ch->etag);
            at[10] = ch->creator != 0u ? ecb->join.nodes[ch->creator - 1u].txnode : 0xFFu;
            at += CHANNEL;
        }
    }
    for (unsigned k = 0u; k < b->stream_count; k++) {
        store_stream(at, &b->streams[k]);
        at += STREAM;
    }
    return size;
}

/* The section goes straight into the tables, empty (ups_ecb__bind_init), checked as it goes: a
 * section that does not fit or contradicts itself fails, and the caller empties them again. */
int ups_ecb__bind_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (size < HEAD) {
        return UPS_ERR_ARGUMENT;
    }
    unsigned channels = get16(in);
    unsigned streams = in[2];
    if (channels > UPS_ECB_CHANNELS || streams > UPS_ECB_STREAMS ||
        size != HEAD + CHANNEL * (size_t)channels + STREAM * (size_t)streams) {
        return UPS_ERR_ARGUMENT;
    }
    const uint8_t *at = in + HEAD;
    for (unsigned i = 0u; i < channels; i++, at += CHANNEL) {
        unsigned etag = get16(at + 8);
        unsigned txnode = at[10];
        if (etag < UPS_ECB__FIRST_ETAG || etag > UPS_ECB__ETAG_MASK ||
            (txnode >= UPS_ECB__MGMT && txnode != 0xFFu) || find_etag(ecb, etag) != NULL ||
            find_uid(ecb, at) != NULL) {
            return UPS_ERR_ARGUMENT;
        }
        ups_ecb_channel_t *ch = &b->channels[i];
        ups_ecb__copy(ch->uid, at, 8u);
        ch->etag = (uint16_t)etag;
        int creator = txnode == 0xFFu ? UPS_ECB__NO_SLOT : ups_ecb__holder(ecb, txnode);
        ch->creator = (uint8_t)(creator + 1); /* NO_SLOT (-1): nobody (0) */
    }
    for (unsigned k = 0u; k < streams; k++, at += STREAM) {
        ups_ecb_stream_t *s = &b->streams[k];
        load_stream(s, at);
        /* bound (so its etag is in range), in order, valid as DECLARE, a priority granted */
        if (find_etag(ecb, s->etag) == NULL || s->txnode >= UPS_ECB__MGMT ||
            (k > 0u && stream_key(s) <= stream_key(s - 1)) || s->period == 0u ||
            s->deadline == 0u || (s->etag < UPS_ECB__LARGE_ETAG ? s->size > 8u : s->size == 0u) ||
            s->priority < 2u || s->priority > 0x7Fu) {
            return UPS_ERR_ARGUMENT;
        }
        for (unsigned j = 0u; j < k; j++) {
            if (b->streams[j].priority == s->priority) {
                return UPS_ERR_ARGUMENT;
            }
        }
    }
    b->stream_count = (uint8_t)streams;
    b->refused_valid = 0u;
    drop_streams(ecb, 0u, NONE); /* of a TxNode nobody holds: gone */
    return UPS_OK;
}

int ups_ecb_channel_users(const ups_ecb_t *ecb, int i, uint8_t subscribers[16],
                          uint8_t publishers[16])
{
    ups_ecb__copy(subscribers, NULL, 16u);
    ups_ecb__copy(publishers, NULL, 16u);
    if ((unsigned)i >= UPS_ECB_CHANNELS || ecb->bind.channels[i].etag == 0u) {
        return -1;
    }
    const ups_ecb_channel_t *ch = &ecb->bind.channels[i];
    for (unsigned j = 0u; j < UPS_ECB_NODES; j++) { /* users are node entries: their TxNodes */
        const ups_ecb_node_t *node = &ecb->join.nodes[j];
        if (node->flags & UPS_ECB__HELD) {
            unsigned t = node->txnode & 0x7Fu;
            subscribers[t >> 3] |= (uint8_t)(has(ch->use[0], j) << (t & 7u));
            publishers[t >> 3] |= (uint8_t)(has(ch->use[1], j) << (t & 7u));
        }
    }
    return ch->etag;
}
