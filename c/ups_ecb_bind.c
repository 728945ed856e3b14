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
#define F_USES_SUB 0x3A00u
#define F_USES_PUB 0x3B00u
#define F_ROSTER_END 0x3C00u
#define BIND_PRIORITY 1u

#define NOBODY 0xFFu
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

static unsigned class_first(unsigned c)
{
    return c == 0u ? UPS_ECB__FIRST_ETAG : UPS_ECB__LARGE_ETAG + ((c - 1u) << 10);
}

static unsigned class_end(unsigned c)
{
    return UPS_ECB__LARGE_ETAG + (c << 10);
}

static int has(const uint8_t *map, int slot)
{
    return (int)(((unsigned)map[(unsigned)slot >> 3] >> ((unsigned)slot & 7u)) & 1u);
}

static void put_bit(uint8_t *map, int slot, int on)
{
    uint8_t bit = (uint8_t)(1u << ((unsigned)slot & 7u));
    map[(unsigned)slot >> 3] = (uint8_t)(on ? map[(unsigned)slot >> 3] | bit
                                            : map[(unsigned)slot >> 3] & (uint8_t)~bit);
}

static int in_use(const ups_ecb_channel_t *ch)
{
    unsigned any = 0u;
    for (unsigned k = 0u; k < UPS_ECB_NODE_BYTES; k++) {
        any |= (unsigned)(ch->sub[k] | ch->pub[k]);
    }
    return any != 0u;
}

static int uses(const ups_ecb_channel_t *ch, int slot)
{
    return has(ch->sub, slot) || has(ch->pub, slot);
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

/* struct copies and shifts through ups_ecb__copy, so that no compiler makes memcpy or memmove
 * calls of them (no C library) */
static void copy_stream(ups_ecb_stream_t *to, const ups_ecb_stream_t *from)
{
    ups_ecb__copy((uint8_t *)to, (const uint8_t *)from, (unsigned)sizeof(*to));
}

static void copy_held(ups_ecb_held_t *to, const ups_ecb_held_t *from)
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

static int find_uid(const ups_ecb_t *ecb, const uint8_t *uid)
{
    for (int i = 0; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag != 0u && ups_ecb__same8(ch->uid, uid)) {
            return i;
        }
    }
    return -1;
}

static int find_etag(const ups_ecb_t *ecb, unsigned etag)
{
    for (int i = 0; i < UPS_ECB_CHANNELS; i++) {
        if (ecb->bind.channels[i].etag == etag) {
            return i;
        }
    }
    return -1;
}

static void send_uid(ups_ecb_t *ecb, unsigned priority, unsigned field, const uint8_t *uid)
{
    ups_ecb__send(ecb, ups_ecb__id(priority, UPS_ECB__MGMT, field), uid, 8u);
}

static void send_bind(ups_ecb_t *ecb, unsigned etag, const uint8_t *uid)
{
    send_uid(ecb, BIND_PRIORITY, etag, uid);
}

static void send_limit(ups_ecb_t *ecb, unsigned txnode, const uint8_t *uid)
{
    send_uid(ecb, 0u, F_LIMIT | txnode, uid);
}

/** Whether this CAN-ECB answers the bus now (a candidate or serving, not standing by). */
static int answering(const ups_ecb_t *ecb)
{
    int role = ups_ecb_role(ecb);
    return role == UPS_ECB_CANDIDATE || role == UPS_ECB_SERVING;
}

/* ---- leases ---------------------------------------------------------------------------------- */

/** Milliseconds of one age step: a sixteenth of the lease, rounded up (0: no lease). Leases
 *  beyond 397 days count as 397 days (an age step stays below 2^31 ms). */
static uint32_t age_unit(const ups_ecb_t *ecb)
{
    uint32_t lease = ecb->cfg.lease_s;
    if (lease <= 4294967u) {
        return (lease * 1000u + 15u) / 16u;
    }
    uint32_t unit = lease / 16u + 1u;
    return unit < 2147483u ? unit * 1000u : 0x7FFFFFFFu;
}

static int past_lease(const ups_ecb_t *ecb, const ups_ecb_channel_t *ch)
{
    return age_unit(ecb) == 0u || ch->age >= AGE_PAST;
}

/** The channel unused longest, past the lease, that no node uses: of size class @p c (or any,
 *  -1), created by node entry @p creator (or anyone, -1); -1 when there is none. */
static int oldest_idle(const ups_ecb_t *ecb, int c, int creator)
{
    int best = -1;
    for (int i = 0; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag == 0u || in_use(ch) || !past_lease(ecb, ch) ||
            (c >= 0 && size_class(ch->etag) != (unsigned)c) ||
            (creator >= 0 && ch->creator != (unsigned)creator)) {
            continue;
        }
        if (best < 0 || ch->age > ecb->bind.channels[best].age) {
            best = i;
        }
    }
    return best;
}

static void forget_etag(ups_ecb_t *ecb, unsigned etag);

/** Unbind the i-th channel, unused past the lease: its etag is free, its creator's quota too. */
static void reclaim(ups_ecb_t *ecb, int i)
{
    ups_ecb_channel_t *ch = &ecb->bind.channels[i];
    forget_etag(ecb, ch->etag);
    ups_ecb__copy((uint8_t *)ch, NULL, (unsigned)sizeof(*ch));
    ch->creator = NOBODY;
    ups_ecb__count(&ecb->counters.reclaimed);
    ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
}

/** A free entry of the table, reclaiming the channel unused longest past the lease if need be;
 *  -1 when none. */
static int free_entry(ups_ecb_t *ecb)
{
    int i = find_etag(ecb, 0u);
    if (i < 0) {
        i = oldest_idle(ecb, -1, -1);
        if (i >= 0) {
            reclaim(ecb, i);
        }
    }
    return i;
}

/** The lowest free etag of size class @p c, else the one unused longest past the lease
 *  (reclaimed); 0 when none. */
static unsigned free_etag(ups_ecb_t *ecb, unsigned c)
{
    unsigned end = class_end(c);
    for (unsigned base = class_first(c); base < end; base += 64u) {
        uint8_t taken[8];
        ups_ecb__copy(taken, NULL, 8u);
        for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
            unsigned e = ecb->bind.channels[i].etag;
            if (e >= base && e < base + 64u) {
                unsigned bit = e - base;
                taken[bit >> 3] = (uint8_t)(taken[bit >> 3] | (1u << (bit & 7u)));
            }
        }
        for (unsigned k = 0u; k < 64u && base + k < end; k++) {
            if ((((unsigned)taken[k >> 3] >> (k & 7u)) & 1u) == 0u) {
                return base + k;
            }
        }
    }
    int i = oldest_idle(ecb, (int)c, -1);
    if (i < 0) {
        return 0u;
    }
    unsigned etag = ecb->bind.channels[i].etag;
    reclaim(ecb, i);
    return etag;
}

static void age_channels(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    uint32_t unit = age_unit(ecb);
    unsigned steps = 0u;
    while (unit != 0u && ups_ecb__since(ecb->now, b->t_aged) >= unit) {
        b->t_aged += unit;
        if (++steps > AGE_PAST) {
            b->t_aged = ecb->now;
        }
    }
    if (unit == 0u) {
        b->t_aged = ecb->now;
    }
    for (unsigned i = 0u; steps > 0u && i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &b->channels[i];
        unsigned age = ch->age + steps;
        ch->age = (uint8_t)(age < 0xFFu ? age : 0xFFu);
    }
}

/* ---- declared streams ------------------------------------------------------------------------ */

static int find_stream(const ups_ecb_t *ecb, unsigned etag, unsigned txnode)
{
    for (int k = 0; k < ecb->bind.stream_count; k++) {
        const ups_ecb_stream_t *s = &ecb->bind.streams[k];
        if (s->etag == etag && s->txnode == txnode) {
            return k;
        }
    }
    return -1;
}

static void drop_stream(ups_ecb_t *ecb, int k)
{
    ups_ecb_bind_t *b = &ecb->bind;
    unsigned room = (unsigned)(sizeof b->streams / sizeof b->streams[0]);
    for (unsigned j = (unsigned)k; j + 1u < b->stream_count && j + 1u < room; j++) {
        copy_stream(&b->streams[j], &b->streams[j + 1u]);
    }
    b->stream_count--;
    b->refused_valid = 0u;
    ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
}

/** The channel left @p etag (it moved, or was reclaimed): the streams declared on it are gone. */
static void forget_etag(ups_ecb_t *ecb, unsigned etag)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (int k = b->stream_count - 1; k >= 0; k--) {
        if (b->streams[k].etag == etag) {
            drop_stream(ecb, k);
        }
    }
    if (get16(b->refuse) == etag) {
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
    ups_ecb__send(ecb, ups_ecb__id(0u, UPS_ECB__MGMT, F_GRANT), data, 8u);
}

static void send_refuse(ups_ecb_t *ecb, const uint8_t *data)
{
    ups_ecb__send(ecb, ups_ecb__id(0u, UPS_ECB__MGMT, F_REFUSE), data, 8u);
}

/** Refuse stream (etag, txnode), naming (miss_etag, miss_txnode) and @p response; remembered
 *  (the answer to the same DECLARE again, and to a forged Grant of the stream). */
static void refuse(ups_ecb_t *ecb, const uint8_t *decl, unsigned txnode, unsigned miss_etag,
                   unsigned miss_txnode, unsigned response)
{
    ups_ecb_bind_t *b = &ecb->bind;
    uint8_t *r = b->refuse;
    r[0] = decl[0];
    r[1] = decl[1];
    r[2] = (uint8_t)txnode;
    r[3] = (uint8_t)miss_txnode;
    r[4] = (uint8_t)(miss_etag >> 8);
    r[5] = (uint8_t)miss_etag;
    r[6] = (uint8_t)(response >> 8);
    r[7] = (uint8_t)response;
    ups_ecb__copy(b->refused_decl, decl, 8u);
    b->refused_valid = 1u;
    ups_ecb__count(&ecb->counters.refused);
    send_refuse(ecb, r);
}

/** Analyse the admitted streams and the new one: Grants, or a Refuse. */
static void decide(ups_ecb_t *ecb, const ups_ecb_stream_t *new_stream, const uint8_t *decl)
{
    ups_ecb_bind_t *b = &ecb->bind;
    ups_ecb_stream_t work[UPS_ECB_STREAMS + 1];
    unsigned count = 0u;
    int placed = 0;
    for (int k = 0; k < b->stream_count; k++) {
        const ups_ecb_stream_t *s = &b->streams[k];
        unsigned key = ((unsigned)s->etag << 7) | s->txnode;
        unsigned new_key = ((unsigned)new_stream->etag << 7) | new_stream->txnode;
        if (key == new_key) {
            continue; /* declared again: replaced */
        }
        if (!placed && key > new_key) {
            copy_stream(&work[count++], new_stream);
            placed = 1;
        }
        copy_stream(&work[count++], s);
    }
    if (!placed) {
        copy_stream(&work[count++], new_stream);
    }
    unsigned txnode = new_stream->txnode;
    if (count > (unsigned)UPS_ECB_STREAMS) {
        ups_ecb__count(&ecb->counters.streams_full);
        refuse(ecb, decl, txnode, new_stream->etag, txnode, 0u);
        return;
    }
    unsigned miss = 0u;
    uint16_t response = UNBOUNDED;
    if (!ups_ecb_rt_admit(work, count, ecb->cfg.bitrate, ecb->cfg.fd, &miss, &response)) {
        if (response == 0u || miss >= count) { /* more streams than priorities */
            refuse(ecb, decl, txnode, new_stream->etag, txnode, 0u);
        } else {
            refuse(ecb, decl, txnode, work[miss].etag, work[miss].txnode, response);
        }
        return;
    }
    for (unsigned j = 0u; j < count; j++) {
        int old = find_stream(ecb, work[j].etag, work[j].txnode);
        if ((work[j].etag == new_stream->etag && work[j].txnode == txnode) || old < 0 ||
            b->streams[old].priority != work[j].priority) {
            send_grant(ecb, &work[j]);
        }
    }
    for (unsigned j = 0u; j < count; j++) {
        copy_stream(&b->streams[j], &work[j]);
    }
    b->stream_count = (uint8_t)count;
    b->refused_valid = 0u;
    if (get16(b->refuse) == new_stream->etag && b->refuse[2] == txnode) {
        ups_ecb__copy(b->refuse, NULL, 8u);
    }
    ups_ecb__count(&ecb->counters.admitted);
    ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
}

static int valid_declaration(unsigned etag, unsigned size, unsigned period, unsigned deadline)
{
    if (etag < UPS_ECB__FIRST_ETAG || etag > UPS_ECB__ETAG_MASK || period == 0u ||
        deadline == 0u) {
        return 0;
    }
    return etag < UPS_ECB__LARGE_ETAG ? size <= 8u : size >= 1u;
}

static void declare(ups_ecb_t *ecb, int slot, unsigned txnode, const uint8_t *data)
{
    ups_ecb_bind_t *b = &ecb->bind;
    ups_ecb_stream_t s;
    s.etag = (uint16_t)get16(data);
    s.txnode = (uint8_t)txnode;
    s.size = data[2];
    s.period = (uint16_t)get16(data + 3);
    s.deadline = (uint16_t)get16(data + 5);
    s.jitter = data[7];
    s.priority = 0u;
    int i = find_etag(ecb, s.etag);
    if (!valid_declaration(s.etag, s.size, s.period, s.deadline) || i < 0 ||
        !has(b->channels[i].pub, slot)) {
        ups_ecb__count(&ecb->counters.malformed); /* as the Python CAN-ECB counts it */
        return;
    }
    int k = find_stream(ecb, s.etag, txnode);
    if (k >= 0 && b->streams[k].size == s.size && b->streams[k].period == s.period &&
        b->streams[k].deadline == s.deadline && b->streams[k].jitter == s.jitter) {
        send_grant(ecb, &b->streams[k]); /* asked again: the same answer, no analysis */
        return;
    }
    if (b->refused_valid && b->refuse[2] == txnode && ups_ecb__same8(b->refused_decl, data)) {
        send_refuse(ecb, b->refuse);
        return;
    }
    if (b->spent[slot] >= DECLARE_BURST) {
        ups_ecb__count(&ecb->counters.limited);
        return;
    }
    b->spent[slot]++;
    decide(ecb, &s, data);
}

/* ---- binding --------------------------------------------------------------------------------- */

/** May node entry @p slot (TxNode @p txnode) use the channel of @p uid (entry @p i, or -1)?
 *  If not, Limit. */
static int within_limit(ups_ecb_t *ecb, int slot, unsigned txnode, int i, const uint8_t *uid)
{
    if (i >= 0 && uses(&ecb->bind.channels[i], slot)) {
        return 1;
    }
    unsigned used = 0u;
    for (unsigned j = 0u; j < UPS_ECB_CHANNELS; j++) {
        used += ecb->bind.channels[j].etag != 0u && uses(&ecb->bind.channels[j], slot);
    }
    if (used < ecb->cfg.max_channels) {
        return 1;
    }
    ups_ecb__count(&ecb->counters.limited);
    send_limit(ecb, txnode, uid);
    return 0;
}

/** May node entry @p slot create a binding of size class @p c? Past its quota, the one it
 *  created that was unused longest is reclaimed, once past the lease; else Limit, counted. */
static int within_quota(ups_ecb_t *ecb, int slot, unsigned txnode, const uint8_t *uid,
                        unsigned c)
{
    unsigned made = 0u;
    for (unsigned j = 0u; j < UPS_ECB_CHANNELS; j++) {
        const ups_ecb_channel_t *ch = &ecb->bind.channels[j];
        made += ch->etag != 0u && ch->creator == (unsigned)slot && size_class(ch->etag) == c;
    }
    if (made < ecb->cfg.quota[c]) {
        return 1;
    }
    int i = oldest_idle(ecb, (int)c, slot);
    if (i >= 0) {
        reclaim(ecb, i);
        return 1;
    }
    ups_ecb__count(&ecb->counters.quota_hit);
    send_limit(ecb, txnode, uid);
    return 0;
}

static void use(ups_ecb_t *ecb, int i, int slot, int publish)
{
    uint8_t *map = publish ? ecb->bind.channels[i].pub : ecb->bind.channels[i].sub;
    if (!has(map, slot)) {
        put_bit(map, slot, 1);
        ups_ecb__note(ecb, UPS_ECB_NOTE_CHANNELS);
    }
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

/** SUB_BIND, PUB_BIND or PUB_BIND(c) (@p kind, the request's etag field) of @p uid. */
static void bind(ups_ecb_t *ecb, int slot, unsigned txnode, unsigned kind, const uint8_t *uid)
{
    unsigned c = kind > PUB_BIND_CLASS ? kind - PUB_BIND_CLASS : 0u;
    int publish = kind != SUB_BIND;
    int i = find_uid(ecb, uid);
    int fits = i >= 0 && size_class(ecb->bind.channels[i].etag) >= c;
    if (ecb->recovering && !fits) {
        hold(ecb, txnode, kind, uid);
        return;
    }
    if (!within_limit(ecb, slot, txnode, i, uid)) {
        return;
    }
    if (!fits) {
        if (!within_quota(ecb, slot, txnode, uid, c)) {
            return;
        }
        unsigned etag = 0u;
        if (i < 0) { /* a new channel: an entry first (one reclaimed frees its etag too) */
            i = free_entry(ecb);
            if (i < 0) {
                ups_ecb__count(&ecb->counters.channels_full);
            }
        }
        if (i >= 0) {
            etag = free_etag(ecb, c);
        }
        if (etag == 0u) {
            ups_ecb__count(&ecb->counters.refused);
            send_uid(ecb, 0u, F_ETAGS_FULL, uid);
            return;
        }
        ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag != 0u) { /* a move to a larger size class */
            ups_ecb__count(&ecb->counters.moved);
            forget_etag(ecb, ch->etag);
        } else {
            ups_ecb__copy(ch->uid, uid, 8u);
        }
        ch->etag = (uint16_t)etag;
        ch->creator = (uint8_t)slot;
        ch->age = 0u;
        ups_ecb__count(&ecb->counters.bound);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    }
    use(ecb, i, slot, publish);
    ecb->bind.channels[i].age = 0u; /* just answered: not unused (no reclaim takes it now) */
    send_bind(ecb, ecb->bind.channels[i].etag, uid);
}

/** The tables' Binds of @p etag and of @p uid where they differ from (etag, uid); how many. */
static unsigned correct(ups_ecb_t *ecb, unsigned etag, const uint8_t *uid)
{
    unsigned sent = 0u;
    int j = find_etag(ecb, etag);
    if (j >= 0) {
        send_bind(ecb, etag, ecb->bind.channels[j].uid);
        sent++;
    }
    int i = find_uid(ecb, uid);
    if (i >= 0 && ecb->bind.channels[i].etag != etag) {
        send_bind(ecb, ecb->bind.channels[i].etag, uid);
        sent++;
    }
    return sent;
}

/** SUB_AT / PUB_AT(etag, uid): a binding a node holds. */
static void holds(ups_ecb_t *ecb, int slot, unsigned txnode, int publish, unsigned etag,
                  const uint8_t *uid)
{
    int i = find_uid(ecb, uid);
    if (i >= 0 && ecb->bind.channels[i].etag == etag) {
        if (within_limit(ecb, slot, txnode, i, uid)) {
            use(ecb, i, slot, publish);
        }
        return;
    }
    if (i < 0 && find_etag(ecb, etag) < 0) {
        if (!within_limit(ecb, slot, txnode, -1, uid) ||
            !within_quota(ecb, slot, txnode, uid, size_class(etag))) {
            return;
        }
        i = free_entry(ecb);
        if (i < 0) {
            ups_ecb__count(&ecb->counters.channels_full);
            return;
        }
        ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        ups_ecb__copy(ch->uid, uid, 8u);
        ch->etag = (uint16_t)etag;
        ch->creator = (uint8_t)slot;
        ch->age = 0u;
        ups_ecb__count(&ecb->counters.adopted);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        use(ecb, i, slot, publish);
        return;
    }
    ups_ecb__count(&ecb->counters.conflicts);
    (void)correct(ecb, etag, uid);
    if (i < 0 && !ecb->recovering) { /* it will ask again: answer it now */
        bind(ecb, slot, txnode, publish ? PUB_BIND : SUB_BIND, uid);
    }
}

static void unsubscribe(ups_ecb_t *ecb, int slot, unsigned txnode, const uint8_t *uid)
{
    ups_ecb_bind_t *b = &ecb->bind;
    unsigned to = 0u;
    for (unsigned h = 0u; h < UPS_ECB_HELD; h++) { /* a SUB_BIND held: dropped */
        const ups_ecb_held_t *held = &b->held[h];
        if (held->kind == SUB_BIND && held->txnode == txnode && ups_ecb__same8(held->uid, uid)) {
            continue;
        }
        if (to != h) {
            copy_held(&b->held[to], held);
        }
        to++;
    }
    for (; to < UPS_ECB_HELD; to++) {
        b->held[to].kind = 0u;
    }
    int i = find_uid(ecb, uid);
    if (i >= 0 && has(b->channels[i].sub, slot)) {
        put_bit(b->channels[i].sub, slot, 0);
        ups_ecb__note(ecb, UPS_ECB_NOTE_CHANNELS);
    }
}

/* ---- the roster ------------------------------------------------------------------------------ */

/** The channel in use with the lowest UID at or (@p after) above @p uid; -1 when none. */
static int next_channel(const ups_ecb_t *ecb, const uint8_t *uid, int after)
{
    int best = -1;
    for (int i = 0; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &ecb->bind.channels[i];
        if (ch->etag == 0u || !in_use(ch)) {
            continue;
        }
        int cmp = uid_cmp(ch->uid, uid);
        if ((cmp > 0 || (cmp == 0 && !after)) &&
            (best < 0 || uid_cmp(ch->uid, ecb->bind.channels[best].uid) < 0)) {
            best = i;
        }
    }
    return best;
}

/** The lowest TxNode above @p last (-1: any) of the node entries in @p map; -1 when none. */
static int next_user(const ups_ecb_t *ecb, const uint8_t *map, int last)
{
    int best = -1;
    for (int j = 0; j < UPS_ECB_NODES; j++) {
        int t = ecb->join.nodes[j].txnode;
        if (t != 0xFF && has(map, j) && t > last && (best < 0 || t < best)) {
            best = t;
        }
    }
    return best;
}

static void roster_end(ups_ecb_t *ecb, const uint8_t *next)
{
    static const uint8_t zero[8] = {0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u};
    unsigned done = next == NULL;
    send_uid(ecb, 0u, F_ROSTER_END | (done << 7) | ecb->bind.r_asker, done ? zero : next);
    ecb->bind.r_active = 0u;
}

/** Start listing the channel after (or at) r_uid, or end the page; 1 when a frame was sent. */
static int roster_channel(ups_ecb_t *ecb, int after)
{
    ups_ecb_bind_t *b = &ecb->bind;
    int i = next_channel(ecb, b->r_uid, after);
    if (i < 0) {
        roster_end(ecb, NULL);
        return 1;
    }
    if (b->r_count >= ROSTER_PAGE) {
        roster_end(ecb, b->channels[i].uid);
        return 1;
    }
    ups_ecb__copy(b->r_uid, b->channels[i].uid, 8u);
    b->r_started = 1u;
    b->r_role = 0u;
    b->r_last = 0xFFu;
    return 0;
}

/** Send the answer's next frame. */
static void roster_step(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (!b->r_started && roster_channel(ecb, 0)) {
        return;
    }
    for (;;) {
        int i = find_uid(ecb, b->r_uid);
        if (i >= 0) {
            const ups_ecb_channel_t *ch = &b->channels[i];
            int last = b->r_last == 0xFFu ? -1 : b->r_last;
            int t = next_user(ecb, b->r_role ? ch->pub : ch->sub, last);
            if (t >= 0) {
                send_uid(ecb, 0u, (b->r_role ? F_USES_PUB : F_USES_SUB) | (unsigned)t, ch->uid);
                b->r_last = (uint8_t)t;
                b->r_count++;
                return;
            }
            if (b->r_role == 0u) {
                b->r_role = 1u;
                b->r_last = 0xFFu;
                continue;
            }
        }
        if (roster_channel(ecb, 1)) {
            return;
        }
    }
}

/** Whether a roster frame waits in the TX queue: the queue sends the lowest identifier first,
 *  so the answer's frames go one at a time to keep their order. */
static int roster_queued(const ups_ecb_t *ecb)
{
    for (unsigned q = 0u; q < ecb->tx_count; q++) {
        uint32_t id = ecb->tx[q].id;
        if ((id >> UPS_ECB__TXNODE_SHIFT) == UPS_ECB__MGMT &&
            (id & UPS_ECB__ETAG_MASK) >= F_USES_SUB &&
            (id & UPS_ECB__ETAG_MASK) < F_ROSTER_END + 0x100u) {
            return 1;
        }
    }
    return 0;
}

static void roster_pump(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (ecb->recovering || !answering(ecb)) {
        return;
    }
    while (b->r_tokens > 0u && ecb->tx_count + ROOM < UPS_ECB_TX_DEPTH &&
           !roster_queued(ecb)) {
        if (!b->r_active) {
            if (b->r_waiting == 0u) {
                return;
            }
            unsigned slot = b->r_queue[0];
            b->r_waiting--;
            ups_ecb__copy(b->r_queue, b->r_queue + 1, b->r_waiting);
            if (ecb->join.nodes[slot].txnode == 0xFFu) {
                continue;
            }
            b->r_asker = ecb->join.nodes[slot].txnode;
            ups_ecb__copy(b->r_uid, b->r_cursor[slot], 8u);
            b->r_started = 0u;
            b->r_count = 0u;
            b->r_active = 1u;
        }
        roster_step(ecb);
        b->r_tokens--;
        ups_ecb__count(&ecb->counters.roster_frames);
    }
}

/** Drop the Roster of node entry @p slot that waits; whether one did. */
static int roster_unqueue(ups_ecb_bind_t *b, int slot)
{
    unsigned to = 0u;
    for (unsigned q = 0u; q < b->r_waiting; q++) {
        if (b->r_queue[q] != (unsigned)slot) {
            b->r_queue[to++] = b->r_queue[q];
        }
    }
    int dropped = to != b->r_waiting;
    b->r_waiting = (uint8_t)to;
    return dropped;
}

static void roster_ask(ups_ecb_t *ecb, int slot, const uint8_t *cursor)
{
    ups_ecb_bind_t *b = &ecb->bind;
    ups_ecb__count(&ecb->counters.rosters);
    if (roster_unqueue(b, slot)) { /* a newer one replaces the one waiting */
        ups_ecb__count(&ecb->counters.roster_replaced);
    }
    ups_ecb__copy(b->r_cursor[slot], cursor, 8u);
    b->r_queue[b->r_waiting++] = (uint8_t)slot;
    roster_pump(ecb);
}

/* ---- the part's entries ---------------------------------------------------------------------- */

void ups_ecb__bind_init(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        b->channels[i].creator = NOBODY;
    }
    b->r_tokens = ROSTER_BURST;
}

void ups_ecb__bind_request(ups_ecb_t *ecb, int slot, uint32_t id, const uint8_t *data)
{
    unsigned priority = (unsigned)(id >> UPS_ECB__PRIO_SHIFT);
    unsigned txnode = (unsigned)(id >> UPS_ECB__TXNODE_SHIFT) & UPS_ECB__MGMT;
    unsigned field = (unsigned)id & UPS_ECB__ETAG_MASK;
    if (slot < 0 || slot >= UPS_ECB_NODES) {
        return;
    }
    if (field >= UPS_ECB__FIRST_ETAG) {
        if (priority <= BIND_PRIORITY) {
            holds(ecb, slot, txnode, priority == BIND_PRIORITY, field, data);
        }
    } else if (priority != 0u) {
        return;
    } else if (field == PUB_BIND || field == SUB_BIND ||
               (field > PUB_BIND_CLASS && field <= PUB_BIND_CLASS + 4u)) {
        bind(ecb, slot, txnode, field, data);
    } else if (field == UNSUB) {
        unsubscribe(ecb, slot, txnode, data);
    } else if (field == DECLARE) {
        declare(ecb, slot, txnode, data);
    } else if (field == ROSTER) {
        roster_ask(ecb, slot, data);
    }
}

void ups_ecb__bind_event(ups_ecb_t *ecb, unsigned etag)
{
    int i = find_etag(ecb, etag);
    if (i >= 0 && etag != 0u) {
        ecb->bind.channels[i].age = 0u;
    }
}

static void forget_slot(ups_ecb_t *ecb, int slot, int creations)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (slot < 0 || slot >= UPS_ECB_NODES) {
        return;
    }
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &b->channels[i];
        if (uses(ch, slot)) {
            put_bit(ch->sub, slot, 0);
            put_bit(ch->pub, slot, 0);
            ups_ecb__note(ecb, UPS_ECB_NOTE_CHANNELS);
        }
        if (creations && ch->etag != 0u && ch->creator == (unsigned)slot) {
            ch->creator = NOBODY;
            ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        }
    }
    unsigned txnode = ecb->join.nodes[slot].txnode;
    for (int k = b->stream_count - 1; k >= 0; k--) {
        if (b->streams[k].txnode == txnode || ups_ecb__holder(ecb, b->streams[k].txnode) < 0) {
            drop_stream(ecb, k);
        }
    }
    if (get16(b->refuse) != 0u && b->refuse[2] == txnode) {
        ups_ecb__copy(b->refuse, NULL, 8u);
        b->refused_valid = 0u;
    }
    (void)roster_unqueue(b, slot);
    b->spent[slot] = 0u;
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
    if (len != 8u) {
        return;
    }
    if (priority == BIND_PRIORITY && field >= UPS_ECB__FIRST_ETAG) { /* Bind */
        int j = find_etag(ecb, field);
        if ((j < 0 || !ups_ecb__same8(ecb->bind.channels[j].uid, data)) &&
            correct(ecb, field, data) > 0u) {
            ups_ecb__count(&ecb->counters.conflicts);
        }
        return;
    }
    if (priority != 0u || (field != F_GRANT && field != F_REFUSE)) {
        return;
    }
    unsigned etag = get16(data);
    unsigned txnode = data[2];
    int k = find_stream(ecb, etag, txnode);
    if (k >= 0) {
        if (field == F_REFUSE || data[3] != ecb->bind.streams[k].priority) {
            ups_ecb__count(&ecb->counters.conflicts);
            send_grant(ecb, &ecb->bind.streams[k]);
        }
    } else if (field == F_GRANT) { /* a stream it has not admitted */
        const uint8_t *r = ecb->bind.refuse;
        uint8_t own[8]; /* naming the stream itself, unbounded */
        ups_ecb__copy(own, data, 3u);
        own[3] = data[2];
        put16(own + 4, etag);
        put16(own + 6, UNBOUNDED);
        ups_ecb__count(&ecb->counters.conflicts);
        send_refuse(ecb, get16(r) == etag && r[2] == txnode ? r : own);
    }
}

/** Answer the requests held in the recovery window, oldest first, as far as the TX queue has
 *  room (each answer is one frame); the rest at the next ticks. */
static void replay(ups_ecb_t *ecb)
{
    ups_ecb_bind_t *b = &ecb->bind;
    for (unsigned done = 0u; !ecb->recovering && answering(ecb) && b->held[0].kind != 0u &&
                             ecb->tx_count + ROOM < UPS_ECB_TX_DEPTH; done++) {
        unsigned kind = b->held[0].kind;
        int i = find_uid(ecb, b->held[0].uid);
        if (done > 0u && i >= 0 && kind > PUB_BIND_CLASS &&
            size_class(b->channels[i].etag) < kind - PUB_BIND_CLASS) {
            break; /* a move: in a call of its own, so that no Bind this call sent is stale
                      in the blob saved after it */
        }
        ups_ecb_held_t held;
        copy_held(&held, &b->held[0]);
        ups_ecb__copy((uint8_t *)&b->held[0], (const uint8_t *)&b->held[1],
                      (unsigned)((UPS_ECB_HELD - 1u) * sizeof(b->held[0])));
        b->held[UPS_ECB_HELD - 1u].kind = 0u;
        int slot = ups_ecb__holder(ecb, held.txnode);
        if (slot >= 0) {
            bind(ecb, slot, held.txnode, held.kind, held.uid);
        }
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
#define STREAM 10u  /* etag, TxNode, size, period, deadline, jitter, priority */

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
    out[0] = (uint8_t)(channels >> 8);
    out[1] = (uint8_t)channels;
    out[2] = b->stream_count;
    uint8_t *at = out + HEAD;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        const ups_ecb_channel_t *ch = &b->channels[i];
        if (ch->etag == 0u) {
            continue;
        }
        ups_ecb__copy(at, ch->uid, 8u);
        at[8] = (uint8_t)(ch->etag >> 8);
        at[9] = (uint8_t)ch->etag;
        at[10] = ch->creator < UPS_ECB_NODES ? ecb->join.nodes[ch->creator].txnode : NOBODY;
        at += CHANNEL;
    }
    for (unsigned k = 0u; k < b->stream_count; k++) {
        const ups_ecb_stream_t *s = &b->streams[k];
        put16(at, s->etag);
        at[2] = s->txnode;
        at[3] = s->size;
        put16(at + 4, s->period);
        put16(at + 6, s->deadline);
        at[8] = s->jitter;
        at[9] = s->priority;
        at += STREAM;
    }
    return size;
}

/** Whether the section @p in of @p channels and @p streams records fits the tables and
 *  contradicts itself nowhere. */
static int valid_section(const uint8_t *in, unsigned channels, unsigned streams)
{
    const uint8_t *ch = in + HEAD;
    for (unsigned i = 0u; i < channels; i++) {
        unsigned etag = get16(ch + i * CHANNEL + 8u);
        unsigned creator = ch[i * CHANNEL + 10u];
        if (etag < UPS_ECB__FIRST_ETAG || etag > UPS_ECB__ETAG_MASK ||
            (creator >= UPS_ECB__MGMT && creator != NOBODY)) {
            return 0;
        }
        for (unsigned j = 0u; j < i; j++) {
            if (get16(ch + j * CHANNEL + 8u) == etag ||
                ups_ecb__same8(ch + j * CHANNEL, ch + i * CHANNEL)) {
                return 0;
            }
        }
    }
    const uint8_t *st = ch + CHANNEL * channels;
    unsigned last_key = 0u;
    for (unsigned k = 0u; k < streams; k++) {
        const uint8_t *s = st + k * STREAM;
        unsigned etag = get16(s);
        unsigned key = (etag << 7) | s[2];
        int bound = 0;
        for (unsigned i = 0u; i < channels; i++) {
            bound |= get16(ch + i * CHANNEL + 8u) == etag;
        }
        if (!bound || s[2] >= UPS_ECB__MGMT || (k > 0u && key <= last_key) ||
            !valid_declaration(etag, s[3], get16(s + 4), get16(s + 6)) || s[9] < 2u ||
            s[9] > 0x7Fu) {
            return 0;
        }
        for (unsigned j = 0u; j < k; j++) {
            if (st[j * STREAM + 9u] == s[9]) {
                return 0;
            }
        }
        last_key = key;
    }
    return 1;
}

int ups_ecb__bind_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size)
{
    ups_ecb_bind_t *b = &ecb->bind;
    if (size < HEAD) {
        return UPS_ERR_ARGUMENT;
    }
    unsigned channels = get16(in);
    unsigned streams = in[2];
    if (channels > UPS_ECB_CHANNELS || streams > UPS_ECB_STREAMS ||
        size != HEAD + CHANNEL * (size_t)channels + STREAM * (size_t)streams ||
        !valid_section(in, channels, streams)) {
        return UPS_ERR_ARGUMENT;
    }
    const uint8_t *at = in + HEAD;
    for (unsigned i = 0u; i < UPS_ECB_CHANNELS; i++) {
        ups_ecb_channel_t *ch = &b->channels[i];
        ups_ecb__copy((uint8_t *)ch, NULL, (unsigned)sizeof(*ch));
        ch->creator = NOBODY;
        if (i < channels) {
            ups_ecb__copy(ch->uid, at, 8u);
            ch->etag = (uint16_t)get16(at + 8u);
            int creator = at[10] == NOBODY ? -1 : ups_ecb__holder(ecb, at[10]);
            ch->creator = creator < 0 ? NOBODY : (uint8_t)creator;
            at += CHANNEL;
        }
    }
    for (unsigned k = 0u; k < streams; k++) {
        ups_ecb_stream_t *s = &b->streams[k];
        s->etag = (uint16_t)get16(at);
        s->txnode = at[2];
        s->size = at[3];
        s->period = (uint16_t)get16(at + 4);
        s->deadline = (uint16_t)get16(at + 6);
        s->jitter = at[8];
        s->priority = at[9];
        at += STREAM;
    }
    b->stream_count = (uint8_t)streams;
    b->refused_valid = 0u;
    for (int k = b->stream_count - 1; k >= 0; k--) { /* of a TxNode nobody holds: gone */
        if (ups_ecb__holder(ecb, b->streams[k].txnode) < 0) {
            drop_stream(ecb, k);
        }
    }
    return UPS_OK;
}

int ups_ecb_channel_use(const ups_ecb_t *ecb, int i, unsigned txnode)
{
    int slot = ups_ecb__holder(ecb, txnode);
    if (i < 0 || i >= UPS_ECB_CHANNELS || slot < 0 || ecb->bind.channels[i].etag == 0u) {
        return 0;
    }
    return has(ecb->bind.channels[i].sub, slot) | (has(ecb->bind.channels[i].pub, slot) << 1);
}
