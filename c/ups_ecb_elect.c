/*
 * libups-ecb: the election among the CAN-ECBs of a bus (docs/protocol.md, "More than one
 * CAN-ECB"): Hello, Serving, Probe, candidacy, takeover, the watch of unanswered requests.
 * The same state machine as the Python CAN-ECB's (broker/_election.py), step for step.
 *
 * A CAN-ECB is a candidate from its Hello until its candidacy ends (its recovery time, at most
 * 2 s), then it serves and says Serving. A Serving outranks a Hello, and of two of a kind the
 * lower instance wins: a candidate stands by on any Serving and on a lower Hello; a serving
 * one stands by only on a lower Serving, and answers every other CAN-ECB frame with its
 * Serving (at most one per second, the Serving gap; one due sooner waits), and beats every
 * 10 s. Standing by it probes every 2 s, and takes over (Hello) after 4 s without a Hello or
 * Serving of another, or when a request it watched (Knock, SUB_BIND, PUB_BIND, PUB_BIND(c);
 * a binding request only from a TxNode its table holds, an Assign of another gave or a CLAIM
 * within 2 s of a Hello: the one serving owes the others no answer) has had no answer for
 * 2.5 s: then it is wary for the rest
 * of its run (as a candidate it stands by for nothing; serving, for a lower Serving only with
 * another's answer heard within 2 s of it, and not while busy).
 *
 * Who calls what: the dispatcher (ups_ecb.c) sets ecb->now, calls ups_ecb__elect_heard() for
 * every CAN-ECB frame it did not send, ups_ecb__elect_asked() for a node's frame while standing
 * by, and ups_ecb__elect_tick() on every tick; it says Hello (and opens the recovery window)
 * when one returns UPS_ECB__SAY_HELLO. At a change to standing by this source itself stops the
 * census and the rosters (ups_ecb__join_stop, ups_ecb__bind_stop); at the change back it clears
 * ecb->started_up (it heard nothing while standing by: it learns the bus anew). Every change of
 * role raises UPS_ECB_NOTE_ROLE.
 */
#include "ups_ecb_internal.h"

/* the timers, ms (docs/protocol.md, Timers) */
#define SERVING_GAP 1000u   /* at most one Serving in answer per this long */
#define PROBE 2000u         /* standing by: Probe this often */
#define TAKEOVER 4000u      /* ... and take over after this long without a Hello or Serving */
#define BEAT 10000u         /* serving: a Serving at least this often, asked or not */
#define MAX_CANDIDACY 2000u /* a candidate serves at most this long after its Hello */
#define ANSWER 2500u        /* standing by: take over when a request had no answer this long */
#define BACKING 2000u       /* wary: stand by only with another's answer this close to it */
#define EARLY 1000u         /* an answer heard up to this long before its request counts */

/* the etag field's status (bits 8-11) of CAN-ECB frames with op 3 */
#define ST_CENSUS 0x0u
#define ST_TXNODES_FULL 0x1u
#define ST_ETAGS_FULL 0x2u
#define ST_HELLO 0x3u
#define ST_SERVING 0x6u
#define ST_FAILED 0x7u
#define ST_LIMIT 0x8u
#define ST_PROBE 0x9u
#define SERVING_FIELD 0x3600u
#define PROBE_FIELD 0x3900u
#define KNOCK_FIELD 0x3F00u

/* ups_ecb_elect_t.t_known[] (and their bits in known) */
#define KNOWN_ANSWERED 0u /* the last Serving in answer */
#define KNOWN_ANSWER 1u   /* the last answer of another to a node */
#define KNOWN_LOWER 2u    /* the last Serving of a lower instance */
#define KNOWN_HELLO 3u    /* the last Hello, its own or another's (the CLAIMs answer it) */

/* what a frame answers (answers()) */
#define KEY_KNOCK 0x01u /* the joiners' Knocks */
#define KEY_UID 0x02u   /* the binding requests of the UID in its data */

/** How long ago time @p i (KNOWN_...) was: the longest there is when none is known. */
static uint32_t ago(const ups_ecb_t *ecb, unsigned i)
{
    const ups_ecb_elect_t *el = &ecb->elect;
    return ((el->known >> i) & 1u) != 0u ? ups_ecb__since(ecb->now, el->t_known[i]) : 0xFFFFFFFFu;
}

static void mark(ups_ecb_t *ecb, unsigned i)
{
    ecb->elect.t_known[i] = ecb->now;
    ecb->elect.known |= (uint8_t)(1u << i);
}

static void set_role(ups_ecb_t *ecb, uint8_t role)
{
    if (ecb->elect.role != role) {
        ecb->elect.role = role;
        ups_ecb__note(ecb, UPS_ECB_NOTE_ROLE);
    }
}

/* ---- the tables of watched requests and heard answers -------------------------------------- */

static int same_key(const ups_ecb_watch_t *w, unsigned knock, const uint8_t *uid)
{
    return knock ? w->knock != 0u : (w->knock == 0u && ups_ecb__same8(w->uid, uid));
}

static int find(const ups_ecb_watch_t *table, unsigned n, unsigned knock, const uint8_t *uid)
{
    for (unsigned i = 0u; i < n; i++) {
        if (same_key(&table[i], knock, uid)) {
            return (int)i;
        }
    }
    return -1;
}

/** Remove @p count entries of @p table (@p n entries) from @p at, keeping the order (a byte
 *  copy down over itself, forward: a loop of entries would be a call of memmove). */
static void drop(ups_ecb_watch_t *table, uint16_t *n, unsigned at, unsigned count)
{
    unsigned after = *n - at - count;
    ups_ecb__copy((uint8_t *)&table[at], (const uint8_t *)&table[at + count],
                  after * (unsigned)sizeof(ups_ecb_watch_t));
    *n = (uint16_t)(*n - count);
}

static void put(ups_ecb_watch_t *w, unsigned knock, const uint8_t *uid, uint32_t t)
{
    w->knock = (uint8_t)(knock != 0u);
    ups_ecb__copy(w->uid, knock ? NULL : uid, 8u);
    w->t = (uint16_t)t;
}

/** Answers heard more than EARLY ago count for no request: forget them (oldest first). */
static void forget_early(ups_ecb_t *ecb)
{
    ups_ecb_elect_t *el = &ecb->elect;
    unsigned stale = 0u;
    while (stale < el->n_answered && ups_ecb__since16(ecb->now, el->answered[stale].t) > EARLY) {
        stale++;
    }
    drop(el->answered, &el->n_answered, 0u, stale);
}

/** An answer to the requests of a key was heard: they are not watched any more, and a request
 *  of that key heard up to EARLY later counts as answered. */
static void answered(ups_ecb_t *ecb, unsigned knock, const uint8_t *uid)
{
    ups_ecb_elect_t *el = &ecb->elect;
    int at = find(el->asked, el->n_asked, knock, uid);
    if (at >= 0) {
        drop(el->asked, &el->n_asked, (unsigned)at, 1u);
    }
    at = find(el->answered, el->n_answered, knock, uid);
    if (at >= 0) {
        drop(el->answered, &el->n_answered, (unsigned)at, 1u);
    }
    forget_early(ecb);
    if (el->n_answered >= UPS_ECB_WATCHED) { /* the oldest goes */
        drop(el->answered, &el->n_answered, 0u, 1u);
    }
    put(&el->answered[el->n_answered], knock, uid, ecb->now);
    el->n_answered++;
}

/** The keys of the requests a CAN-ECB frame answers (KEY_...). */
static unsigned answers(uint32_t id)
{
    uint32_t priority = id >> UPS_ECB__PRIO_SHIFT;
    uint32_t field = id & UPS_ECB__ETAG_MASK;
    if (((id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu) != UPS_ECB__MGMT) {
        return 0u;
    }
    if (priority == 1u) {
        return KEY_UID; /* Bind */
    }
    if (priority != 0u) {
        return 0u;
    }
    switch (field >> 12) {
    case 1u: /* Query */
    case 2u: /* Offer, Assign */
        return KEY_KNOCK;
    case 3u:
        switch ((field >> 8) & 0xFu) {
        case ST_CENSUS:
        case ST_TXNODES_FULL: return KEY_KNOCK;
        case ST_FAILED: return KEY_KNOCK | KEY_UID; /* of a node id (a join) or of a UID */
        case ST_ETAGS_FULL:
        case ST_LIMIT: return KEY_UID;
        default: return 0u;
        }
    default: return 0u;
    }
}

/* ---- the roles ----------------------------------------------------------------------------- */

static unsigned candidate(ups_ecb_t *ecb)
{
    ups_ecb_elect_t *el = &ecb->elect;
    if (el->role == UPS_ECB_STANDBY) {
        ecb->started_up = 0u; /* it heard nothing while standing by: learn the bus anew */
    }
    el->n_asked = 0u;
    ups_ecb__copy(el->assigned, NULL, 16u); /* its recovery learns the TxNodes in use */
    mark(ecb, KNOWN_HELLO);
    el->t_role = ecb->now;
    set_role(ecb, UPS_ECB_CANDIDATE);
    return UPS_ECB__SAY_HELLO;
}

static unsigned stand_by(ups_ecb_t *ecb)
{
    ups_ecb_elect_t *el = &ecb->elect;
    el->n_asked = 0u;
    el->t_role = ecb->now;
    el->t_probe = ecb->now;
    el->due = 0u;
    set_role(ecb, UPS_ECB_STANDBY);
    ups_ecb__join_stop(ecb); /* it answers nothing: no census, no rosters */
    ups_ecb__bind_stop(ecb);
    return 0u;
}

static void announce(ups_ecb_t *ecb)
{
    ecb->elect.t_serving = ecb->now;
    ups_ecb__send8(ecb, SERVING_FIELD, ecb->instance);
}

/** Serving in answer: now, or (within the gap of the last answer) once the gap has passed. The
 *  Serving at a candidacy's end and the beat answer nobody: they do not count. */
static unsigned serve(ups_ecb_t *ecb)
{
    ups_ecb_elect_t *el = &ecb->elect;
    el->due = 1u;
    if (ago(ecb, KNOWN_ANSWERED) >= SERVING_GAP) {
        mark(ecb, KNOWN_ANSWERED);
        el->due = 0u;
        announce(ecb);
    }
    return 0u;
}

/** Whether instance @p a (8 bytes, big-endian) is lower than @p b. */
static int below(const uint8_t *a, const uint8_t *b)
{
    for (unsigned i = 0u; i < 8u; i++) {
        if (a[i] != b[i]) {
            return a[i] < b[i];
        }
    }
    return 0;
}

/* ---- the calls ----------------------------------------------------------------------------- */

void ups_ecb__elect_start(ups_ecb_t *ecb)
{
    uint16_t recovery = ecb->cfg.recovery_ms;
    ecb->elect.candidacy = (uint16_t)(recovery < MAX_CANDIDACY ? recovery : MAX_CANDIDACY);
    (void)candidate(ecb); /* the caller says Hello */
}

unsigned ups_ecb__elect_heard(ups_ecb_t *ecb, unsigned status, const uint8_t *instance,
                              uint32_t id, const uint8_t *data, int busy)
{
    ups_ecb_elect_t *el = &ecb->elect;
    if (instance != NULL && ups_ecb__same8(instance, ecb->instance)) {
        return 0u; /* its own instance: an echo or a forger, not a rival */
    }
    if (instance == NULL) { /* an answer to a node (another CAN-ECB's, or a forger's) */
        unsigned keys = answers(id);
        uint32_t field = id & UPS_ECB__ETAG_MASK;
        mark(ecb, KNOWN_ANSWER);
        if ((keys & KEY_KNOCK) != 0u && (field & 0xF080u) == 0x2000u) { /* an Assign (no Offer) */
            el->assigned[(field >> 3) & 0xFu] |= (uint8_t)(1u << (field & 7u)); /* owed answers */
        }
        if (keys & KEY_KNOCK) {
            answered(ecb, 1u, NULL);
        }
        if ((keys & KEY_UID) != 0u && data != NULL) {
            answered(ecb, 0u, data);
        } else {
            forget_early(ecb);
        }
    }
    int hello = instance != NULL && status == ST_HELLO;
    int serving = instance != NULL && status == ST_SERVING;
    if (hello) {
        mark(ecb, KNOWN_HELLO); /* the nodes claim: the CLAIMs that follow are held */
    }
    int lower = (hello || serving) && below(instance, ecb->instance);
    switch (el->role) {
    case UPS_ECB_STANDBY:
        if (hello || serving) {
            el->t_role = ecb->now; /* one serves, or is about to */
        }
        return 0u;
    case UPS_ECB_CANDIDATE:
        if (el->wary) {
            return 0u; /* it serves its candidacy out: what it holds is answered then */
        }
        return serving || (hello && lower) ? stand_by(ecb) : 0u;
    case UPS_ECB_SERVING:
        lower = serving && lower;
        if (lower && !el->wary) {
            return stand_by(ecb);
        }
        if (lower) {
            mark(ecb, KNOWN_LOWER);
        }
        if (el->wary && !busy && ago(ecb, KNOWN_LOWER) <= BACKING &&
            ago(ecb, KNOWN_ANSWER) <= BACKING) {
            return stand_by(ecb); /* a lower one serves too, and answers what this one does */
        }
        /* a lower claim with no answers behind it yet gets nothing; anything else a Serving */
        return lower ? 0u : serve(ecb);
    default: return 0u;
    }
}

unsigned ups_ecb__elect_asked(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    ups_ecb_elect_t *el = &ecb->elect;
    uint32_t field = id & UPS_ECB__ETAG_MASK;
    uint32_t txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned knock;
    if (el->role != UPS_ECB_STANDBY || (id >> UPS_ECB__PRIO_SHIFT) != 0u) {
        return 0u;
    }
    if (txnode != UPS_ECB__MGMT && field == 0x0004u && len == 8u &&
        ago(ecb, KNOWN_HELLO) <= MAX_CANDIDACY) { /* a CLAIM answers a Hello: one adopts it */
        el->assigned[txnode >> 3] |= (uint8_t)(1u << (txnode & 7u));
    }
    if (txnode == UPS_ECB__MGMT && field == KNOCK_FIELD && len == 0u) {
        knock = 1u;
    } else if (txnode != UPS_ECB__MGMT && len == 8u && data != NULL &&
               (field == 0x0001u || field == 0x0002u || (field >= 0x0009u && field <= 0x000Cu))) {
        knock = 0u; /* PUB_BIND, SUB_BIND, PUB_BIND(c) of the UID in data */
        if (ups_ecb__holder(ecb, txnode) == UPS_ECB__NO_SLOT &&
            (el->assigned[txnode >> 3] & (1u << (txnode & 7u))) == 0u) {
            return 0u; /* nobody holds it, as far as it knows: the one serving owes no answer */
        }
    } else {
        return 0u;
    }
    if (find(el->asked, el->n_asked, knock, data) >= 0) {
        return 0u; /* watched since its first time */
    }
    int early = find(el->answered, el->n_answered, knock, data);
    if (early >= 0 && ups_ecb__since16(ecb->now, el->answered[early].t) <= EARLY) {
        return 0u; /* its answer came first (frames of two senders may cross) */
    }
    if (el->n_asked >= UPS_ECB_WATCHED) {
        ups_ecb__count(&ecb->counters.watched_full);
        return 0u;
    }
    put(&el->asked[el->n_asked], knock, data, ecb->now);
    el->n_asked++;
    return 0u;
}

unsigned ups_ecb__elect_tick(ups_ecb_t *ecb)
{
    ups_ecb_elect_t *el = &ecb->elect;
    uint32_t now = ecb->now;
    unsigned verdict = 0u;
    switch (el->role) {
    case UPS_ECB_CANDIDATE:
        if (ups_ecb__since(now, el->t_role) >= el->candidacy) {
            set_role(ecb, UPS_ECB_SERVING);
            announce(ecb); /* standing-by CAN-ECBs hear that one serves */
        }
        break;
    case UPS_ECB_SERVING:
        if (el->due && ago(ecb, KNOWN_ANSWERED) >= SERVING_GAP) {
            verdict = serve(ecb); /* the Serving owed */
        } else if (ups_ecb__since(now, el->t_serving) >= BEAT) {
            announce(ecb);
        }
        break;
    case UPS_ECB_STANDBY:
        if (el->n_asked > 0u && ups_ecb__since16(now, el->asked[0].t) >= ANSWER) {
            el->wary = 1u; /* a claim without answers: a forger's, or a broken CAN-ECB's */
            ups_ecb__count(&ecb->counters.unanswered_takeovers);
            verdict = candidate(ecb);
        } else if (ups_ecb__since(now, el->t_role) >= TAKEOVER) {
            verdict = candidate(ecb); /* no other CAN-ECB said Serving for 4 s */
        } else if (ups_ecb__since(now, el->t_probe) >= PROBE) {
            el->t_probe = now;
            ups_ecb__send8(ecb, PROBE_FIELD, ecb->instance);
        }
        break;
    default: break;
    }
    /* times too old to matter are forgotten, so that the wrapping clock never brings them back */
    for (unsigned i = 0u; i < 4u; i++) {
        uint32_t keep = i == KNOWN_ANSWERED ? (el->due ? 0xFFFFFFFFu : SERVING_GAP - 1u)
                        : i == KNOWN_HELLO  ? MAX_CANDIDACY
                                            : BACKING;
        if (ago(ecb, i) > keep) {
            el->known &= (uint8_t)~(1u << i);
        }
    }
    forget_early(ecb);
    return verdict;
}

/** Milliseconds left of a timer of @p length that started @p since ms ago (0: over). */
static uint32_t left(uint32_t since, uint32_t length)
{
    return since >= length ? 0u : length - since;
}

static uint32_t sooner(uint32_t a, uint32_t b)
{
    return a < b ? a : b;
}

uint32_t ups_ecb__elect_next(const ups_ecb_t *ecb)
{
    const ups_ecb_elect_t *el = &ecb->elect;
    uint32_t now = ecb->now;
    uint32_t next = 0xFFFFFFFFu;
    switch (el->role) {
    case UPS_ECB_CANDIDATE: return left(ups_ecb__since(now, el->t_role), el->candidacy);
    case UPS_ECB_SERVING:
        if (el->due) {
            next = left(ago(ecb, KNOWN_ANSWERED), SERVING_GAP);
        }
        return sooner(next, left(ups_ecb__since(now, el->t_serving), BEAT));
    case UPS_ECB_STANDBY:
        if (el->n_asked > 0u) {
            next = left(ups_ecb__since16(now, el->asked[0].t), ANSWER);
        }
        next = sooner(next, left(ups_ecb__since(now, el->t_role), TAKEOVER));
        return sooner(next, left(ups_ecb__since(now, el->t_probe), PROBE));
    default: return next;
    }
}
