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

/* numbers as the blob and the instance keep them: big-endian */
static void put32(uint8_t *out, uint32_t v)
{
    for (unsigned i = 4u; i-- > 0u;) {
        out[i] = (uint8_t)v;
        v >>= 8;
    }
}

static uint32_t get32(const uint8_t *in)
{
    uint32_t v = 0u;
    for (unsigned i = 0u; i < 4u; i++) {
        v = (v << 8) | in[i];
    }
    return v;
}

/** The Python CAN-ECB's. */
static const ups_ecb_config_t DEFAULTS = {
    500000u, 0u, 2000u, 86400u, UPS_ECB_CHANNELS, {1024u, 64u, 64u, 64u, 64u},
};

void ups_ecb_default_config(ups_ecb_config_t *cfg)
{
    *cfg = DEFAULTS;
}

/** Empty tables (before a restore, and after a refused one). */
static void empty(ups_ecb_t *ecb)
{
    ups_ecb__join_init(ecb);
    ups_ecb__bind_init(ecb);
}

int ups_ecb_init(ups_ecb_t *ecb, const ups_ecb_config_t *cfg, uint64_t instance)
{
    ups_ecb__copy((uint8_t *)ecb, NULL, (unsigned)sizeof(*ecb));
    if (cfg == NULL) {
        cfg = &DEFAULTS;
    }
    if (cfg->bitrate == 0u || cfg->recovery_ms - 100u > 10000u - 100u ||
        cfg->lease_s - 1u >= LEASE_MAX_S) {
        return UPS_ERR_ARGUMENT;
    }
    ecb->cfg = *cfg;
    put32(ecb->instance, (uint32_t)(instance >> 32));
    put32(&ecb->instance[4], (uint32_t)instance);
    empty(ecb);
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
#define BLOB_MAGIC 0x55505365u   /* "UPSe" */
#define BLOB_VERSION 0x0100u     /* bytes 4-5: the version, 0 */
#define BLOB_FIXED (BLOB_HEADER + 8u) /* the header, B and the CRC */

/** CRC-32 (IEEE 802.3, reflected, as zlib's crc32) of @p n bytes. */
static uint32_t crc32(const uint8_t *data, size_t n)
{
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        crc ^= data[i];
        for (unsigned k = 0; k < 8u; k++) {
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
        }
    }
    return ~crc;
}

size_t ups_ecb_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    if (cap < UPS_ECB_BLOB_MAX) {
        return 0u;
    }
    size_t j = ups_ecb__join_save(ecb, out + BLOB_HEADER, cap - BLOB_FIXED);
    uint8_t *bind = out + BLOB_HEADER + j;
    size_t b = ups_ecb__bind_save(ecb, bind + 4u, cap - BLOB_FIXED - j);
    size_t n = BLOB_FIXED + j + b;
    put32(out, BLOB_MAGIC);
    put32(&out[4], (BLOB_VERSION << 16) | (uint32_t)j);
    put32(&out[8], (uint32_t)n);
    put32(bind, (uint32_t)b);
    put32(&out[n - 4u], crc32(out, n - 4u));
    return n;
}

/** Whether @p blob holds (its header, lengths and CRC), and its sections were taken back. */
static int restored(ups_ecb_t *ecb, const uint8_t *blob, size_t size)
{
    if (blob == NULL || size < BLOB_FIXED || size > UPS_ECB_BLOB_MAX) {
        return 0;
    }
    uint32_t version = get32(&blob[4]);
    size_t j = version & 0xFFFFu;
    size_t b = size - BLOB_FIXED - j; /* wraps when j is too long: checked first */
    return get32(blob) == BLOB_MAGIC && version >> 16 == BLOB_VERSION &&
           get32(&blob[8]) == size && get32(&blob[size - 4u]) == crc32(blob, size - 4u) &&
           j <= size - BLOB_FIXED && get32(&blob[BLOB_HEADER + j]) == b &&
           ups_ecb__join_restore(ecb, blob + BLOB_HEADER, j) == UPS_OK &&
           (b == 0u || ups_ecb__bind_restore(ecb, blob + BLOB_HEADER + j + 4u, b) == UPS_OK);
}

int ups_ecb_restore(ups_ecb_t *ecb, const uint8_t *blob, size_t size)
{
    empty(ecb);
    if (restored(ecb, blob, size)) {
        return UPS_OK;
    }
    empty(ecb); /* empty tables: the bus is relearnt from the Hello answers */
    ups_ecb__count(&ecb->counters.blob_refused);
    return UPS_ERR_ARGUMENT;
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

/** Take the time; whether the CAN-ECB was started. */
static int running(ups_ecb_t *ecb, uint32_t now_ms)
{
    ecb->now = now_ms;
    return ecb->elect.role != UPS_ECB_STOPPED;
}

void ups_ecb_start(ups_ecb_t *ecb, uint32_t now_ms)
{
    if (ecb->elect.role != UPS_ECB_STOPPED) {
        return;
    }
    ecb->now = now_ms;
    ecb->t_unknown_hello = now_ms - HELLO_GAP; /* a stray may have its Hello at once */
    ups_ecb__join_started(ecb);
    ups_ecb__elect_start(ecb);
    hello(ecb);
}

/** A request from TxNode @p txnode, which no node holds: counted (unassigned), remembered as a
 *  stray, and Hello again (at most once per Hello gap, not in a recovery window). */
static void unassigned(ups_ecb_t *ecb, unsigned txnode)
{
    ups_ecb__count(&ecb->counters.unassigned);
    ecb->strays[(txnode & 0x7Fu) / 8u] |= (uint8_t)(1u << (txnode % 8u));
    if (!ecb->recovering && ups_ecb__since(ecb->now, ecb->t_unknown_hello) >= HELLO_GAP) {
        ecb->t_unknown_hello = ecb->now;
        hello(ecb);
    }
}

/* ---- receiving ----------------------------------------------------------------------------- */

#define K_MALFORMED 0
#define K_ECB 1     /* a frame only a CAN-ECB sends */
#define K_STAGE 2
#define K_KNOCK 3
#define K_CLAIM 4
#define K_REQUEST 5 /* any other node frame: PUB_BIND, SUB_BIND, UNSUB, DECLARE, Roster, ... */

/** The OR of @p n bytes (0: all zero). */
static unsigned ors(const uint8_t *d, unsigned n)
{
    unsigned all = 0u;
    for (unsigned i = 0u; i < n; i++) {
        all |= d[i];
    }
    return all;
}

/** Whether the 2 bytes at @p etag are an event etag (0x0010..0x3FFF). */
static int etag_ok(const uint8_t *etag)
{
    return (unsigned)(((unsigned)etag[0] << 8 | etag[1]) - UPS_ECB__FIRST_ETAG) <=
           UPS_ECB__ETAG_MASK - UPS_ECB__FIRST_ETAG;
}

static int stream_ok(const uint8_t *etag, unsigned txnode)
{
    return etag_ok(etag) && txnode < 127u;
}

/* The fields of a node's request (etag field < 0x0010, priority 0, 8 bytes): PUB_BIND 1,
 * SUB_BIND 2, UNSUB 3, CLAIM 4, DECLARE 5, Roster 6, PUB_BIND(c) 9..12. */
#define NODE_FIELDS 0x1E7Eu
#define DECLARE 0x0005u

/** A node's management frame (TxNode < 0x7F), as ups/_canproto.py decodes it. */
static int node_kind(unsigned prio, unsigned field, const uint8_t *d, unsigned len)
{
    if (len != 8u) {
        return K_MALFORMED;
    }
    if (field >= UPS_ECB__FIRST_ETAG) { /* SUB_AT, PUB_AT (of priority 0 or 1: management) */
        return K_REQUEST;
    }
    if (prio != 0u || !((NODE_FIELDS >> field) & 1u)) {
        return K_MALFORMED;
    }
    if (field == DECLARE) { /* a large channel (0x3000..) declares its size, 1..255 */
        int large = d[0] >= (UPS_ECB__LARGE_ETAG >> 8);
        if (!etag_ok(d) || (large ? d[2] == 0u : d[2] > 8u) || ors(&d[3], 2u) == 0u ||
            ors(&d[5], 2u) == 0u) {
            return K_MALFORMED;
        }
    }
    return field == CLAIM ? K_CLAIM : K_REQUEST;
}

/* The rows of the CAN-ECB's frames of priority 0 but the Query (etag field 0xOS.., O the op, S
 * the status of op 3), one byte each: bits 0-1 the range of the field's low byte (below 1, 16,
 * 127 or 256), ROW_FLAG: its bit 7 is a flag, out of the range, ROW_DATA: 8 data bytes (else
 * none), bits 4-5 a check of the data (ROW_GRANT, ROW_REFUSE, ROW_END), bits 6-7 the kind
 * (K_ECB, K_STAGE, K_KNOCK; 0: no row, malformed). */
#define LOW_ZERO 0u
#define LOW_EPOCH 1u
#define LOW_TXNODE 2u
#define LOW_ANY 3u
#define ROW_FLAG 0x04u
#define ROW_DATA 0x08u
#define ROW_GRANT 0x10u
#define ROW_REFUSE 0x20u
#define ROW_END 0x30u
#define ROW_ECB (K_ECB << 6)
#define ROW_STAGE ((unsigned)K_STAGE << 6)
#define ROW_KNOCK ((unsigned)K_KNOCK << 6)

static const uint8_t STATUS_ROWS[16] = {
    ROW_ECB | LOW_EPOCH,                           /* 0 Census */
    ROW_ECB | ROW_DATA,                            /* 1 TxNodesFull */
    ROW_ECB | ROW_DATA,                            /* 2 EtagsFull */
    ROW_ECB | ROW_DATA,                            /* 3 Hello */
    ROW_ECB | ROW_DATA | ROW_GRANT,                /* 4 Grant */
    ROW_ECB | ROW_DATA | ROW_REFUSE,               /* 5 Refuse */
    ROW_ECB | ROW_DATA,                            /* 6 Serving */
    ROW_ECB | ROW_DATA,                            /* 7 Failed */
    ROW_ECB | ROW_DATA | LOW_TXNODE,               /* 8 Limit */
    ROW_ECB | ROW_DATA,                            /* 9 Probe */
    ROW_ECB | ROW_DATA | LOW_TXNODE,               /* A Uses (subscribes) */
    ROW_ECB | ROW_DATA | LOW_TXNODE,               /* B Uses (publishes) */
    ROW_ECB | ROW_DATA | ROW_END | ROW_FLAG | LOW_TXNODE, /* C RosterEnd */
    0u,
    0u,
    ROW_KNOCK,                                     /* F Knock */
};

/** A Query: the prefix's last nibble in the field (@p arg), the rest of the prefix in the data,
 *  every nibble after it zero. */
static int query_ok(unsigned arg, const uint8_t *d)
{
    unsigned stage = (arg >> 4) & 0xFu;
    unsigned at = stage / 2u;
    unsigned odd = stage & 1u; /* the low nibble of d[at], else its high one */
    unsigned nibble = arg & 0xFu;
    return stage != 15u && (d[at] & (odd ? 0x0Fu : 0xFFu)) == (odd ? nibble : nibble << 4) &&
           ors(&d[at + 1u], 7u - at) == 0u;
}

/** What a management frame is (K_...), or K_MALFORMED when it matches no row of the tables. */
static int kind_of(uint32_t id, const uint8_t *d, unsigned len)
{
    static const uint8_t largest[4] = {0u, 15u, 126u, 255u};
    unsigned prio = id >> UPS_ECB__PRIO_SHIFT; /* 29 bits: at most 0xFF */
    unsigned field = id & UPS_ECB__ETAG_MASK;
    if (((id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu) != UPS_ECB__MGMT) {
        return node_kind(prio, field, d, len);
    }
    unsigned op = field >> 12;
    unsigned status = (field >> 8) & 0xFu;
    unsigned row = ROW_ECB | ROW_DATA | LOW_ANY; /* Bind, Query */
    if (prio != 0u) {
        if (prio > 1u || field < UPS_ECB__FIRST_ETAG) {
            return K_MALFORMED;
        }
    } else if (op == 1u) {
        if (!query_ok(field & 0xFFFu, d)) {
            return K_MALFORMED;
        }
    } else if (op == 3u) {
        row = STATUS_ROWS[status];
    } else if (op == 2u) { /* Offer, Assign */
        row = status == 0u ? ROW_ECB | ROW_DATA | ROW_FLAG | LOW_TXNODE : 0u;
    } else {
        row = ROW_STAGE | LOW_ANY;
    }
    unsigned low = field & (row & ROW_FLAG ? 0x7Fu : 0xFFu);
    unsigned check = row & ROW_END;
    if ((row >> 6) == 0u || low > largest[row & 3u] || len != (row & ROW_DATA ? 8u : 0u) ||
        ((check == ROW_GRANT || check == ROW_REFUSE) &&
         (!stream_ok(d, d[2]) ||
          (check == ROW_GRANT ? ors(&d[4], 4u) != 0u : !stream_ok(&d[4], d[3])))) ||
        (check == ROW_END && (field & 0x80u) && ors(d, 8u) != 0u)) {
        return K_MALFORMED; /* a complete RosterEnd names no next */
    }
    return (int)(row >> 6);
}

/** A CAN-ECB frame's key (ups_ecb_echo_t.key): its identifier and length in 16 bits. */
static unsigned echo_key(uint32_t id, unsigned len)
{
    return (id & UPS_ECB__ETAG_MASK) | ((id >> UPS_ECB__PRIO_SHIFT) != 0u ? 0u : 0x4000u) |
           (len != 0u ? 0x8000u : 0u);
}

/** Whether the CAN-ECB frame (TxNode 0x7F, priority 0 or 1, 0 or 8 bytes: checked) @p key,
 *  @p data is one this CAN-ECB sent (queued, or one of the last UPS_ECB_ECHOES sent within
 *  ECHO_WINDOW): its own, heard again. Only a CAN-ECB frame can be: it sends no node's frame,
 *  nor Stage or Knock. */
static int own(ups_ecb_t *ecb, unsigned key, const uint8_t *data)
{
    for (unsigned i = 0; i < ecb->tx_count; i++) {
        if (echo_key(ecb->tx[i].id, ecb->tx_len[i]) == key && ups_ecb__same8(ecb->tx[i].data, data)) {
            return 1;
        }
    }
#if UPS_ECB_ECHOES > 0
    for (unsigned i = 0; i < UPS_ECB_ECHOES; i++) {
        ups_ecb_echo_t *e = &ecb->echo[i];
        if (e->key == key && ups_ecb__same8(e->data, data) &&
            ups_ecb__since16(ecb->now, e->t) < ECHO_WINDOW) {
            e->key = 0u; /* heard once */
            return 1;
        }
    }
#endif
    return 0;
}

/* Hello, Serving, Probe: the status frames that name an instance (their bits) */
#define CLAIMS ((1u << 0x3u) | (1u << 0x6u) | (1u << 0x9u))

static void on_ecb_frame(ups_ecb_t *ecb, uint32_t id, const uint8_t *d, unsigned len)
{
    if (own(ecb, echo_key(id, len), d)) {
        return; /* its own, heard again */
    }
    unsigned status = (id >> 8) & 0xFu;
    const uint8_t *claim = NULL;
    if ((id >> 12) == 0x1FFu && ((CLAIMS >> status) & 1u)) { /* priority 0, TxNode 0x7F, op 3 */
        if (ups_ecb__same8(d, ecb->instance)) {
            return; /* its own */
        }
        claim = d;
    }
    ups_ecb__count(&ecb->counters.foreign_ecb_frames);
    if (ecb->elect.role != UPS_ECB_STANDBY && claim == NULL) {
        ups_ecb__join_correct(ecb, id, d);
        ups_ecb__bind_correct(ecb, id, d, len);
    }
    int busy = ecb->recovering || ups_ecb__join_busy(ecb);
    if ((id >> UPS_ECB__PRIO_SHIFT) != 0u) {
        status = 0xFFu; /* a Bind */
    }
    elected(ecb, ups_ecb__elect_heard(ecb, status, claim, id, d, busy));
}

void ups_ecb_rx(ups_ecb_t *ecb, uint32_t now_ms, const ups_frame_t *frame)
{
    if (!running(ecb, now_ms)) {
        return; /* not started: it listens from its Hello on */
    }
    uint32_t id = frame->id;
    unsigned len = frame->len;
    unsigned txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned field = id & UPS_ECB__ETAG_MASK;
    /* not UPS: not a 29-bit data frame; a management frame is a classic one */
    int foreign = (frame->flags & (UPS_FRAME_RTR | UPS_FRAME_ERR | UPS_FRAME_EXT)) !=
                      UPS_FRAME_EXT ||
                  id > 0x1FFFFFFFu || len > UPS_MTU;
    int management = (id >> 22) == 0u /* priority 0 or 1 */ || txnode == UPS_ECB__MGMT ||
                     field < UPS_ECB__FIRST_ETAG;
    /* cppcheck-suppress knownConditionTrueFalse ; a longer one exists where UPS_MTU is 64 */
    if (management && ((frame->flags & UPS_FRAME_FD) != 0u || len > 8u)) {
        foreign = 1;
    }
    if (foreign) {
        ups_ecb__count(&ecb->counters.foreign);
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
    ups_ecb__copy(d, frame->data, len);
    int kind = kind_of(id, d, len);
    if (kind == K_MALFORMED) {
        ups_ecb__count(&ecb->counters.malformed);
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
    if (kind >= K_CLAIM) {
        ups_ecb__count(&ecb->counters.requests);
    }
    if (kind != K_REQUEST) { /* Stage, Knock, CLAIM */
        if (ups_ecb__join_rx(ecb, id, d, len)) {
            unassigned(ecb, txnode);
        }
        return;
    }
    int slot = ups_ecb__holder(ecb, txnode);
    if (slot == UPS_ECB__NO_SLOT) {
        unassigned(ecb, txnode);
        return;
    }
    ups_ecb__bind_request(ecb, slot, id, d);
}

/* ---- time ---------------------------------------------------------------------------------- */

void ups_ecb_tick(ups_ecb_t *ecb, uint32_t now_ms)
{
    if (!running(ecb, now_ms)) {
        return;
    }
    (void)ups_ecb__age(now_ms, &ecb->t_unknown_hello);
#if UPS_ECB_ECHOES > 0
    for (unsigned i = 0; i < UPS_ECB_ECHOES; i++) { /* past its window an echo is none (its */
        ups_ecb_echo_t *e = &ecb->echo[i];           /* 16-bit time would look fresh again */
        if (ups_ecb__since16(now_ms, e->t) >= ECHO_WINDOW) { /* 65.5 s later) */
            e->key = 0u;
        }
    }
#endif
    /* the election first: a candidacy that ends with the recovery window serves (Serving)
       before it answers what the window held (the Python CAN-ECB's timers fire in that
       order); the queue sends the lowest identifier first, so the window ends a tick later */
    unsigned role = ecb->elect.role;
    elected(ecb, ups_ecb__elect_tick(ecb));
    if (role == ecb->elect.role && ecb->recovering &&
        ups_ecb__since(now_ms, ecb->t_recovery) >= ecb->cfg.recovery_ms) {
        ecb->recovering = 0u;
        ups_ecb__copy(ecb->strays, NULL, (unsigned)sizeof(ecb->strays));
        if (role != UPS_ECB_STANDBY) {
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
#if UPS_ECB_ECHOES > 0
    if (ecb->tx_count != 0u) { /* remembered: heard again, it is known for its own */
        unsigned at = ecb->echo_next;
        ups_ecb_echo_t *e = &ecb->echo[at];
        e->key = (uint16_t)echo_key(ecb->tx_head.id, ecb->tx_head.len);
        e->t = (uint16_t)ecb->now;
        ups_ecb__copy(e->data, ecb->tx_head.data, 8u);
        ecb->echo_next = (uint16_t)(at + 1u < UPS_ECB_ECHOES ? at + 1u : 0u);
    }
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
    if ((unsigned)i >= UPS_ECB_NODES || !(ecb->join.nodes[i].flags & UPS_ECB__HELD)) {
        return -1;
    }
    *node_id = ups_ecb__get64(ecb->join.nodes[i].node_id);
    return ecb->join.nodes[i].txnode;
}

int ups_ecb_channel(const ups_ecb_t *ecb, int i, uint64_t *uid)
{
    if ((unsigned)i >= UPS_ECB_CHANNELS || ecb->bind.channels[i].etag == 0u) {
        return -1;
    }
    *uid = ups_ecb__get64(ecb->bind.channels[i].uid);
    return ecb->bind.channels[i].etag;
}
