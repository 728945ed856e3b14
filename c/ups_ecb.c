/*
 * libups-ecb: the dispatcher (receiving and its checks, the life cycle, Hello and the recovery
 * window, the timers' entry, the blob) on top of ups_ecb_join.c, ups_ecb_bind.c and
 * ups_ecb_elect.c. broker/can_ecb.py is the same in Python.
 *
 * Receiving: a frame that is not a 29-bit data frame, or a CAN FD management frame, is
 * foreign. A frame of a node's TxNode renews that TxNode's lease; an event frame renews its
 * etag's. A management frame is checked as ups/_canproto.py's decode checks it (its row, its
 * data length, its ranges and padding): one that matches no row is malformed, counted, and
 * goes no further. Then:
 *   - a frame this CAN-ECB sent (heard again through an echo: it is queued, or is one of the
 *     last UPS_ECB_ECHOES sent in the last second, identical), and a Hello, Serving or Probe
 *     with its own instance: ignored;
 *   - any other CAN-ECB frame: counted (foreign_ecb_frames); while not standing by, what it
 *     contradicts is corrected (the join's and the bind's corrections); the election hears it;
 *   - standing by: every other management frame goes to the election (it watches that the
 *     one serving answers), and nothing else;
 *   - Stage, Knock, CLAIM: the join's; any other request from a TxNode a node holds: the
 *     bind's (it holds what must wait for the end of a recovery window); from a TxNode no
 *     node holds: counted (unassigned), remembered as a stray, and Hello again at most once
 *     per Hello gap (10 s), outside a recovery window.
 */
#include "ups_ecb_internal.h"

#define HELLO_GAP 10000u /* ms: at most one Hello per this long for unknown TxNodes */
#define ECHO_WINDOW 1000u /* ms: a frame sent this lately and heard again is an echo */
#define LEASE_MAX_S 1000000u /* s: in ms, it fits 32 bits */

#define HELLO_FIELD 0x3300u
#define CLAIM 0x0004u

void ups_ecb_default_config(ups_ecb_config_t *cfg)
{
    cfg->bitrate = 500000u;
    cfg->fd = 0u;
    cfg->recovery_ms = 2000u;
    cfg->lease_s = 86400u;
    cfg->max_channels = UPS_ECB_CHANNELS;
    cfg->quota[0] = 1024u;
    for (unsigned c = 1u; c < 5u; c++) {
        cfg->quota[c] = 64u;
    }
}

int ups_ecb_init(ups_ecb_t *ecb, const ups_ecb_config_t *cfg, uint64_t instance)
{
    ups_ecb__copy((uint8_t *)ecb, NULL, (unsigned)sizeof(*ecb));
    if (cfg != NULL) {
        if (cfg->bitrate == 0u || cfg->recovery_ms < 100u || cfg->recovery_ms > 10000u ||
            cfg->lease_s == 0u || cfg->lease_s > LEASE_MAX_S) {
            return UPS_ERR_ARGUMENT;
        }
        ecb->cfg = *cfg;
    } else {
        ups_ecb_default_config(&ecb->cfg);
    }
    ups_ecb__put64(ecb->instance, instance);
    ups_ecb__join_init(ecb);
    ups_ecb__bind_init(ecb);
    return UPS_OK;
}

/* ---- the blob -----------------------------------------------------------------------------
 *
 * Format 1, all numbers big-endian:
 *
 *   offset   size  what
 *   0        4     magic "UPSe" (0x55 0x50 0x53 0x65)
 *   4        1     format version: 1
 *   5        1     0 (reserved)
 *   6        2     J: the length of the join's section
 *   8        4     N: the length of the whole blob, header and CRC included (N = 20 + J + B)
 *   12       J     the join's section (ups_ecb_join.c): per held node entry, 10 bytes: the
 *                  entry's index, its TxNode, its node id
 *   12+J     4     B: the length of the bind's section
 *   16+J     B     the bind's section (ups_ecb_bind.c: etags by UID and creator, streams)
 *   N-4      4     CRC-32 (IEEE 802.3, as zlib's crc32) of bytes 0 .. N-5
 *
 * A blob whose magic, version, lengths or CRC do not hold, or whose sections do not fit
 * these tables or contradict themselves, is refused as a whole (blob_refused).
 */

#define BLOB_HEADER 12u
#define BLOB_VERSION 1u

static void put32(uint8_t *out, uint32_t v)
{
    out[0] = (uint8_t)(v >> 24);
    out[1] = (uint8_t)(v >> 16);
    out[2] = (uint8_t)(v >> 8);
    out[3] = (uint8_t)v;
}

static uint32_t get32(const uint8_t *in)
{
    return ((uint32_t)in[0] << 24) | ((uint32_t)in[1] << 16) | ((uint32_t)in[2] << 8) | in[3];
}

size_t ups_ecb_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    if (cap < UPS_ECB_BLOB_MAX) {
        return 0u;
    }
    size_t j = ups_ecb__join_save(ecb, out + BLOB_HEADER, cap - BLOB_HEADER - 8u);
    size_t at = BLOB_HEADER + j;
    size_t b = ups_ecb__bind_save(ecb, out + at + 4u, cap - at - 8u);
    size_t n = at + 4u + b + 4u;
    out[0] = 0x55u;
    out[1] = 0x50u;
    out[2] = 0x53u;
    out[3] = 0x65u;
    out[4] = BLOB_VERSION;
    out[5] = 0u;
    out[6] = (uint8_t)(j >> 8);
    out[7] = (uint8_t)j;
    put32(&out[8], (uint32_t)n);
    put32(&out[at], (uint32_t)b);
    put32(&out[n - 4u], ups_ecb__crc32(0u, out, n - 4u));
    return n;
}

static int restore(ups_ecb_t *ecb, const uint8_t *blob, size_t size)
{
    if (blob == NULL || size < BLOB_HEADER + 8u || size > UPS_ECB_BLOB_MAX) {
        return UPS_ERR_ARGUMENT;
    }
    if (blob[0] != 0x55u || blob[1] != 0x50u || blob[2] != 0x53u || blob[3] != 0x65u ||
        blob[4] != BLOB_VERSION || blob[5] != 0u || get32(&blob[8]) != size ||
        get32(&blob[size - 4u]) != ups_ecb__crc32(0u, blob, size - 4u)) {
        return UPS_ERR_ARGUMENT;
    }
    size_t j = ((size_t)blob[6] << 8) | blob[7];
    if (j > size - BLOB_HEADER - 8u) {
        return UPS_ERR_ARGUMENT;
    }
    size_t at = BLOB_HEADER + j;
    size_t b = get32(&blob[at]);
    if (b != size - at - 8u) {
        return UPS_ERR_ARGUMENT;
    }
    if (ups_ecb__join_restore(ecb, blob + BLOB_HEADER, j) != UPS_OK) {
        return UPS_ERR_ARGUMENT;
    }
    if (b > 0u && ups_ecb__bind_restore(ecb, blob + at + 4u, b) != UPS_OK) {
        return UPS_ERR_ARGUMENT;
    }
    return UPS_OK;
}

int ups_ecb_restore(ups_ecb_t *ecb, const uint8_t *blob, size_t size)
{
    ups_ecb__join_init(ecb);
    ups_ecb__bind_init(ecb);
    if (restore(ecb, blob, size) != UPS_OK) {
        ups_ecb__join_init(ecb); /* empty tables: the bus is relearnt from the Hello answers */
        ups_ecb__bind_init(ecb);
        ups_ecb__count(&ecb->counters.blob_refused);
        return UPS_ERR_ARGUMENT;
    }
    return UPS_OK;
}

/* ---- life cycle ---------------------------------------------------------------------------- */

/** Say Hello and listen for the recovery time (at start, and when the tables are behind). */
static void hello(ups_ecb_t *ecb)
{
    ecb->recovering = 1u;
    ecb->t_recovery = ecb->now;
    ups_ecb__send8(ecb, HELLO_FIELD, ecb->instance);
}

static void elected(ups_ecb_t *ecb, unsigned verdict)
{
    if (verdict & UPS_ECB__SAY_HELLO) {
        hello(ecb);
    }
}

void ups_ecb_start(ups_ecb_t *ecb, uint32_t now_ms)
{
    if (ecb->elect.role != UPS_ECB_STOPPED) {
        return;
    }
    ecb->now = now_ms;
    ups_ecb__join_started(ecb);
    ups_ecb__elect_start(ecb);
    hello(ecb);
}

void ups_ecb__unassigned(ups_ecb_t *ecb, unsigned txnode)
{
    ups_ecb__count(&ecb->counters.unassigned);
    ecb->strays[(txnode & 0x7Fu) / 8u] |= (uint8_t)(1u << (txnode % 8u));
    if (!ecb->recovering &&
        (!ecb->hello_gap || ups_ecb__since(ecb->now, ecb->t_unknown_hello) >= HELLO_GAP)) {
        ecb->hello_gap = 1u;
        ecb->t_unknown_hello = ecb->now;
        hello(ecb);
    }
}

int ups_ecb__stray(const ups_ecb_t *ecb, unsigned txnode)
{
    return ((unsigned)ecb->strays[(txnode & 0x7Fu) / 8u] >> (txnode % 8u)) & 1u;
}

/* ---- receiving ----------------------------------------------------------------------------- */

#define K_MALFORMED 0
#define K_ECB 1     /* a frame only a CAN-ECB sends */
#define K_STAGE 2
#define K_KNOCK 3
#define K_CLAIM 4
#define K_REQUEST 5 /* any other node frame: PUB_BIND, SUB_BIND, UNSUB, DECLARE, Roster, ... */

static int stream_ok(const uint8_t *etag, unsigned txnode)
{
    unsigned e = ((unsigned)etag[0] << 8) | etag[1];
    return e >= UPS_ECB__FIRST_ETAG && e <= UPS_ECB__ETAG_MASK && txnode < 127u;
}

/* The fields of a node's request (etag field < 0x0010, priority 0, 8 bytes): PUB_BIND 1,
 * SUB_BIND 2, UNSUB 3, Roster 6, PUB_BIND(c) 9..12 (DECLARE 5 and CLAIM 4 have their own). */
#define REQUEST_FIELDS 0x1E4Eu

/** A node's management frame (TxNode < 0x7F), as ups/_canproto.py decodes it. */
static int node_kind(unsigned prio, unsigned field, const uint8_t *d, unsigned len)
{
    if (field >= UPS_ECB__FIRST_ETAG) { /* SUB_AT, PUB_AT */
        return prio <= 1u && len == 8u ? K_REQUEST : K_MALFORMED;
    }
    if (prio != 0u || len != 8u) {
        return K_MALFORMED;
    }
    if (field == 0x0005u) { /* DECLARE */
        unsigned etag = ((unsigned)d[0] << 8) | d[1];
        unsigned largest = etag < UPS_ECB__LARGE_ETAG ? 8u : 0xFFu;
        int ok = etag >= UPS_ECB__FIRST_ETAG && etag <= UPS_ECB__ETAG_MASK && d[2] <= largest &&
                 (d[2] != 0u || etag < UPS_ECB__LARGE_ETAG) && (d[3] | d[4]) != 0u &&
                 (d[5] | d[6]) != 0u;
        return ok ? K_REQUEST : K_MALFORMED;
    }
    if ((REQUEST_FIELDS >> field) & 1u) {
        return K_REQUEST;
    }
    return field == CLAIM ? K_CLAIM : K_MALFORMED;
}

/* The rows of the status frames (etag field 0x3S.., S the status), one byte each: bits 0-1 the
 * range of the field's low byte (LOW_ZERO: 0, LOW_EPOCH: < 16, LOW_TXNODE: < 127, LOW_ROSTER:
 * < 127 after bit 7, its "complete" flag), ST_DATA: 8 data bytes (else none), bits 3-4 a
 * check of the data (ST_GRANT, ST_REFUSE, ST_END), ST_KNOCK: a Knock, ST_NONE: no row. */
#define LOW_ZERO 0u
#define LOW_EPOCH 1u
#define LOW_TXNODE 2u
#define LOW_ROSTER 3u
#define ST_DATA 0x04u
#define ST_GRANT 0x08u
#define ST_REFUSE 0x10u
#define ST_END 0x18u
#define ST_KNOCK 0x20u
#define ST_NONE 0x40u

static const uint8_t STATUS_ROWS[16] = {
    LOW_EPOCH,                     /* 0 Census */
    ST_DATA,                       /* 1 TxNodesFull */
    ST_DATA,                       /* 2 EtagsFull */
    ST_DATA,                       /* 3 Hello */
    ST_DATA | ST_GRANT,            /* 4 Grant */
    ST_DATA | ST_REFUSE,           /* 5 Refuse */
    ST_DATA,                       /* 6 Serving */
    ST_DATA,                       /* 7 Failed */
    ST_DATA | LOW_TXNODE,          /* 8 Limit */
    ST_DATA,                       /* 9 Probe */
    ST_DATA | LOW_TXNODE,          /* A Uses (subscribes) */
    ST_DATA | LOW_TXNODE,          /* B Uses (publishes) */
    ST_DATA | ST_END | LOW_ROSTER, /* C RosterEnd */
    ST_NONE,
    ST_NONE,
    ST_KNOCK,                      /* F Knock */
};

static int status_kind(unsigned status, unsigned low, const uint8_t *d, unsigned len)
{
    static const uint8_t limit[4] = {1u, 16u, 127u, 127u};
    unsigned row = STATUS_ROWS[status];
    unsigned range = row & 3u;
    if ((row & ST_NONE) || ((range == LOW_ROSTER ? low & 0x7Fu : low) >= limit[range]) ||
        len != (row & ST_DATA ? 8u : 0u)) {
        return K_MALFORMED;
    }
    unsigned check = row & ST_END;
    if ((check == ST_GRANT && ((d[4] | d[5] | d[6] | d[7]) != 0u || !stream_ok(d, d[2]))) ||
        (check == ST_REFUSE && (!stream_ok(d, d[2]) || !stream_ok(&d[4], d[3]))) ||
        (check == ST_END && (low & 0x80u) &&
         (d[0] | d[1] | d[2] | d[3] | d[4] | d[5] | d[6] | d[7]) != 0u)) {
        return K_MALFORMED; /* a complete RosterEnd names no next */
    }
    return row & ST_KNOCK ? K_KNOCK : K_ECB;
}

/** What a management frame is (K_...), or K_MALFORMED when it matches no row of the tables. */
static int kind_of(uint32_t id, const uint8_t *d, unsigned len)
{
    unsigned prio = (id >> UPS_ECB__PRIO_SHIFT) & 0xFFu;
    unsigned txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned field = id & UPS_ECB__ETAG_MASK;
    if (txnode != UPS_ECB__MGMT) {
        return node_kind(prio, field, d, len);
    }
    if (prio == 1u) { /* Bind */
        return field >= UPS_ECB__FIRST_ETAG && len == 8u ? K_ECB : K_MALFORMED;
    }
    if (prio != 0u) {
        return K_MALFORMED;
    }
    unsigned op = field >> 12;
    unsigned arg = field & 0xFFFu;
    unsigned stage = (arg >> 4) & 0xFu;
    if (op == 0u) {
        return len == 0u ? K_STAGE : K_MALFORMED;
    }
    if (op == 1u) { /* Query: the prefix's last nibble in the field, the rest zero */
        unsigned bad = len != 8u || stage == 15u;
        for (unsigned s = stage; s < 16u; s++) { /* nibble s of the data */
            unsigned nibble = (unsigned)(d[s / 2u] >> (s & 1u ? 0u : 4u)) & 0xFu;
            bad |= nibble != (s == stage ? (arg & 0xFu) : 0u);
        }
        return bad ? K_MALFORMED : K_ECB;
    }
    if (op == 2u) { /* Offer, Assign */
        return (arg & ~0x80u) < 127u && len == 8u ? K_ECB : K_MALFORMED;
    }
    return status_kind(arg >> 8, arg & 0xFFu, d, len);
}

#if UPS_ECB_ECHOES > 0
/** A frame's key in echo[]: its identifier, and bit 31 when it has 8 data bytes (the CAN-ECB's
 *  frames have 0 or 8). */
static uint32_t echo_key(uint32_t id, unsigned len)
{
    return id | (len != 0u ? 0x80000000u : 0u);
}
#endif

/** Whether the frame @p id, @p len, @p data is one this CAN-ECB sent (queued, or one of the
 *  last UPS_ECB_ECHOES sent within ECHO_WINDOW): its own, heard again. */
static int own(ups_ecb_t *ecb, uint32_t id, unsigned len, const uint8_t *data)
{
    for (unsigned i = 0; i < ecb->tx_count; i++) {
        const ups_ecb_frame_t *q = &ecb->tx[i];
        if (q->id == id && ecb->tx_len[i] == len) {
            unsigned diff = 0;
            for (unsigned k = 0; k < len; k++) {
                diff |= (unsigned)(q->data[k] ^ data[k]);
            }
            if (diff == 0u) {
                return 1;
            }
        }
    }
#if UPS_ECB_ECHOES > 0
    uint32_t key = echo_key(id, len);
    for (unsigned i = 0; i < UPS_ECB_ECHOES && (len == 0u || len == 8u); i++) {
        if (ecb->echo[i].key[0] == (uint16_t)(key >> 16) && ecb->echo[i].key[1] == (uint16_t)key &&
            (len == 0u || ups_ecb__same8(ecb->echo[i].data, data)) &&
            ups_ecb__since16(ecb->now, ecb->echo[i].t) < ECHO_WINDOW) {
            ecb->echo[i].key[0] = 0u; /* heard once */
            ecb->echo[i].key[1] = 0u;
            return 1;
        }
    }
#endif
    return 0;
}

static void on_ecb_frame(ups_ecb_t *ecb, uint32_t id, const uint8_t *d, unsigned len)
{
    unsigned field = id & UPS_ECB__ETAG_MASK;
    unsigned prio = (id >> UPS_ECB__PRIO_SHIFT) & 0xFFu;
    unsigned status = (field >> 8) & 0xFu;
    int claim = prio == 0u && field >> 12 == 3u && (status == 0x3u || status == 0x6u ||
                                                      status == 0x9u); /* Hello, Serving, Probe */
    if (claim && ups_ecb__same8(d, ecb->instance)) {
        return; /* its own */
    }
    ups_ecb__count(&ecb->counters.foreign_ecb_frames);
    if (ecb->elect.role != UPS_ECB_STANDBY && !claim) {
        ups_ecb__join_correct(ecb, id, d);
        ups_ecb__bind_correct(ecb, id, d, len);
    }
    int busy = ecb->recovering || ups_ecb__join_busy(ecb);
    elected(ecb, ups_ecb__elect_heard(ecb, prio == 0u ? status : 0xFFu, claim ? d : NULL, id, d,
                                      busy));
}

void ups_ecb_rx(ups_ecb_t *ecb, uint32_t now_ms, const ups_frame_t *frame)
{
    ecb->now = now_ms;
    if (ecb->elect.role == UPS_ECB_STOPPED) {
        return; /* not started: it listens from its Hello on */
    }
    uint32_t id = frame->id;
    if ((frame->flags & (UPS_FRAME_RTR | UPS_FRAME_ERR)) != 0u ||
        (frame->flags & UPS_FRAME_EXT) == 0u || id > 0x1FFFFFFFu || frame->len > UPS_MTU) {
        ups_ecb__count(&ecb->counters.foreign);
        return;
    }
    unsigned prio = (id >> UPS_ECB__PRIO_SHIFT) & 0xFFu;
    unsigned txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned field = id & UPS_ECB__ETAG_MASK;
    int management = prio < 2u || txnode == UPS_ECB__MGMT || field < UPS_ECB__FIRST_ETAG;
    /* cppcheck-suppress knownConditionTrueFalse ; a longer one exists where UPS_MTU is 64 */
    if (management && ((frame->flags & UPS_FRAME_FD) != 0u || frame->len > 8u)) {
        ups_ecb__count(&ecb->counters.foreign); /* management frames are classic frames */
        return;
    }
    if (txnode != UPS_ECB__MGMT) {
        ups_ecb__join_seen(ecb, txnode); /* its lease starts again */
    }
    if (!management) {
        ups_ecb__bind_event(ecb, field);
        return;
    }
    uint8_t d[8] = {0};
    ups_ecb__copy(d, frame->data, frame->len);
    unsigned len = frame->len;
    int kind = kind_of(id, d, len);
    if (kind == K_MALFORMED) {
        ups_ecb__count(&ecb->counters.malformed);
        return;
    }
    if (txnode == UPS_ECB__MGMT && own(ecb, id, len, d)) {
        return;
    }
    if (kind == K_ECB) {
        on_ecb_frame(ecb, id, d, len);
        return;
    }
    if (ecb->elect.role == UPS_ECB_STANDBY) { /* answers nothing; watches the one serving */
        elected(ecb, ups_ecb__elect_asked(ecb, id, d, len));
        return;
    }
    if (kind == K_STAGE || kind == K_KNOCK) {
        ups_ecb__join_rx(ecb, id, d, len);
        return;
    }
    ups_ecb__count(&ecb->counters.requests);
    if (kind == K_CLAIM) {
        ups_ecb__join_rx(ecb, id, d, len);
        return;
    }
    int slot = ups_ecb__holder(ecb, txnode);
    if (slot == UPS_ECB__NO_SLOT) {
        ups_ecb__unassigned(ecb, txnode);
        return;
    }
    ups_ecb__bind_request(ecb, slot, id, d);
}

/* ---- time ---------------------------------------------------------------------------------- */

void ups_ecb_tick(ups_ecb_t *ecb, uint32_t now_ms)
{
    ecb->now = now_ms;
    if (ecb->elect.role == UPS_ECB_STOPPED) {
        return;
    }
    (void)ups_ecb__age(now_ms, &ecb->t_unknown_hello);
    /* the election first: a candidacy that ends with the recovery window serves (Serving)
       before it answers what the window held (the Python CAN-ECB's timers fire in that
       order); the queue sends the lowest identifier first, so the window ends a tick later */
    int role = ecb->elect.role;
    elected(ecb, ups_ecb__elect_tick(ecb));
    if (role == ecb->elect.role && ecb->recovering && ups_ecb__since(now_ms, ecb->t_recovery) >= ecb->cfg.recovery_ms) {
        ecb->recovering = 0u;
        ups_ecb__copy(ecb->strays, NULL, (unsigned)sizeof(ecb->strays));
        if (ecb->elect.role != UPS_ECB_STANDBY) {
            ecb->started_up = 1u;
            ups_ecb__bind_recovered(ecb);
            ups_ecb__join_recovered(ecb);
        }
    }
    ups_ecb__join_tick(ecb);
    ups_ecb__bind_tick(ecb);
}

/* ---- sending ------------------------------------------------------------------------------- */

const ups_frame_t *ups_ecb_tx_peek(const ups_ecb_t *ecb)
{
    return ecb->tx_count > 0u ? &ecb->tx_head : NULL;
}

void ups_ecb_tx_pop(ups_ecb_t *ecb)
{
    if (ecb->tx_count == 0u) {
        return;
    }
#if UPS_ECB_ECHOES > 0
    unsigned at = ecb->echo_next;
    uint32_t key = echo_key(ecb->tx_head.id, ecb->tx_head.len);
    ecb->echo[at].key[0] = (uint16_t)(key >> 16);
    ecb->echo[at].key[1] = (uint16_t)key;
    ecb->echo[at].t = (uint16_t)ecb->now;
    ups_ecb__copy(ecb->echo[at].data, ecb->tx_head.data, 8u);
    ecb->echo_next = (uint16_t)((at + 1u) % UPS_ECB_ECHOES);
#endif
    ups_ecb__pop(ecb);
}

/* ---- the small calls ----------------------------------------------------------------------- */

unsigned ups_ecb_notes(ups_ecb_t *ecb)
{
    unsigned notes = ecb->notes;
    ecb->notes = 0u;
    return notes;
}

int ups_ecb_role(const ups_ecb_t *ecb)
{
    return ecb->elect.role;
}

const ups_ecb_counters_t *ups_ecb_counters(const ups_ecb_t *ecb)
{
    return &ecb->counters;
}

int ups_ecb_node(const ups_ecb_t *ecb, int i, uint64_t *node_id)
{
    if (i < 0 || i >= UPS_ECB_NODES || !(ecb->join.nodes[i].flags & UPS_ECB__HELD)) {
        return -1;
    }
    *node_id = ups_ecb__get64(ecb->join.nodes[i].node_id);
    return ecb->join.nodes[i].txnode;
}

int ups_ecb_channel(const ups_ecb_t *ecb, int i, uint64_t *uid)
{
    if (i < 0 || i >= UPS_ECB_CHANNELS || ecb->bind.channels[i].etag == 0u) {
        return -1;
    }
    *uid = ups_ecb__get64(ecb->bind.channels[i].uid);
    return ecb->bind.channels[i].etag;
}
