/*
 * libups-ecb: TxNodes by node id, the census (Knock, Census, Query, Stage), Offers, CLAIM,
 * Assign, moves, TxNodesFull (docs/protocol.md, *Joining* and *Restarts*; broker/_census.py and
 * broker/_txnodes.py are the same in Python).
 *
 * The node table holds every node id the CAN-ECB knows: held (durable), offered, or lapsed
 * (an Offer nobody claimed in time, kept for a late claim). A new node id takes an unused
 * entry, else the one of the oldest lapsed Offer, else the entry of the lowest TxNode on
 * probation (adopted from a stray's CLAIM, or given to a stray's id moved in a later window;
 * silent since), else that of the TxNode silent longest past the lease (both reclaimed); else
 * TxNodesFull. Its TxNode is the lowest no entry uses (the reclaimed one's when reclaimed).
 * The Python CAN-ECB keeps up to 127 lapsed Offers beside 127 TxNodes; here they share the
 * UPS_ECB_NODES entries and give way first. The entries keep no adoption time: of those on
 * probation the lowest TxNode goes first (as in Python), not the one adopted earliest.
 *
 * The census walks the joiners' ids by queries, each in one of 16 epochs (used round robin,
 * as the Python CAN-ECB does), at most UPS_ECB_QUERIES open at once; a closed query stays in
 * its slot, remembered for its late answers (reopened when it had none, raising the slack),
 * until its slot is needed. What a query heard is kept per stage in 4 bits (one nibble) and
 * two bitmaps (heard, several), with the set of nibbles of the first stage with several:
 * all that reading it needs.
 */
#include "ups_ecb_internal.h"

#define NIBBLES 16u
#define TXNODES 127u
#define Q_OPEN 0x10u   /* a query's tag: its state (high nibble), or 0 (free), with its epoch */
#define Q_CLOSED 0x20u
#define Q_STATE 0xF0u

/* timers (ms; docs/protocol.md, *Timers*) */
#define FIRST_MAX 250u
#define FIRST_MIN 30u
#define QUIET 40u
#define LONGEST 2000u
#define QUARANTINE 40u
#define SLACK_MAX 4000u
#define SLACK_HALF_LIFE 2000u
#define LATE_QUORUM 4u
#define OFFER_TIMEOUT 1000u
#define RETRIES 3u
#define RETRY_BUDGET 64u
#define MAX_QUERIES 1024u

/* the fields of the join's frames */
#define OP_QUERY 1u
#define OP_ASSIGN 2u
#define OP_STATUS 3u
#define ST_TXNODES_FULL 1u
#define ST_FAILED 7u
#define OFFER_BIT 0x80u

static unsigned nibble_at(const uint8_t *id, unsigned s)
{
    return (unsigned)(id[s / 2u] >> ((s & 1u) ? 0u : 4u)) & 0x0Fu;
}

/** Set nibble @p s of @p id to @p n (0..15). */
static void set_nibble(uint8_t *id, unsigned s, unsigned n)
{
    unsigned shift = (s & 1u) ? 0u : 4u;
    id[s / 2u] = (uint8_t)((id[s / 2u] & ~(0x0Fu << shift)) | (n << shift));
}

/** The branches of a group of children @p set: one per nibble, or the prefix itself (set 0). */
static unsigned branches(unsigned set)
{
    unsigned n = set == 0u;
    for (; set != 0u; set &= set - 1u) {
        n++;
    }
    return n;
}

/** Count @p n in @p counter (one by one: it saturates). */
static void count_n(UPS_ECB_COUNTER_T *counter, unsigned n)
{
    for (; n > 0u; n--) {
        ups_ecb__count(counter);
    }
}

/* ==== the node table ====================================================================== */

void ups_ecb__join_init(ups_ecb_t *ecb)
{
    ups_ecb__copy((uint8_t *)&ecb->join, NULL, (unsigned)sizeof(ecb->join));
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ecb->join.nodes[i].txnode = 0xFFu;
    }
    ecb->join.rtt = 25u;
}

/** The first entry but @p except whose TxNode is @p txnode and which has a flag of @p flags (any
 *  entry when 0), or UPS_ECB__NO_SLOT. */
static int with_txnode(const ups_ecb_t *ecb, unsigned txnode, int except, unsigned flags)
{
    for (int i = 0; i < UPS_ECB_NODES; i++) {
        const ups_ecb_node_t *node = &ecb->join.nodes[i];
        if (i != except && node->txnode == txnode && (flags == 0u || (node->flags & flags))) {
            return i;
        }
    }
    return UPS_ECB__NO_SLOT;
}

int ups_ecb__holder(const ups_ecb_t *ecb, unsigned txnode)
{
    return with_txnode(ecb, txnode, UPS_ECB__NO_SLOT, UPS_ECB__HELD);
}

static int entry_of(const ups_ecb_t *ecb, const uint8_t *node_id)
{
    for (int i = 0; i < UPS_ECB_NODES; i++) {
        const ups_ecb_node_t *node = &ecb->join.nodes[i];
        if (node->txnode != 0xFFu && ups_ecb__same8(node->node_id, node_id)) {
            return i;
        }
    }
    return UPS_ECB__NO_SLOT;
}

/** Nobody else holds @p txnode, and it is offered to nobody but entry @p slot. */
static int free_for(const ups_ecb_t *ecb, unsigned txnode, int slot)
{
    return with_txnode(ecb, txnode, slot, UPS_ECB__HELD | UPS_ECB__OFFERED) == UPS_ECB__NO_SLOT;
}

/** Entry @p node is @p node_id's, with @p txnode and @p flags, its age 0. */
static void set_entry(ups_ecb_node_t *node, const uint8_t *node_id, unsigned txnode,
                      unsigned flags)
{
    ups_ecb__copy(node->node_id, node_id, 8u);
    node->txnode = (uint8_t)txnode;
    node->flags = (uint8_t)flags;
    node->age = 0u;
}

void ups_ecb__join_started(ups_ecb_t *ecb)
{
    ecb->join.t_aged = ecb->now;
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ecb->join.nodes[i].age = 0u; /* the leases count from the start */
    }
}

void ups_ecb__join_seen(ups_ecb_t *ecb, unsigned txnode)
{
    int slot = ups_ecb__holder(ecb, txnode);
    if (slot != UPS_ECB__NO_SLOT) {
        ecb->join.nodes[slot].age = 0u;
        ecb->join.nodes[slot].flags &= (uint8_t)~UPS_ECB__PROBATION; /* it speaks: a node's */
    }
}

/** The entry a node id without one takes: an unused one, else a lapsed Offer's (the oldest when
 *  @p reclaim, else the first), else (when @p reclaim) the one of the lowest TxNode on
 *  probation, else the one whose TxNode is silent longest past the lease; UPS_ECB__NO_SLOT
 *  when none. */
static int vacant_entry(const ups_ecb_t *ecb, int reclaim)
{
    int slot = UPS_ECB__NO_SLOT;
    unsigned best = 0u;
    for (int i = 0; i < UPS_ECB_NODES; i++) {
        const ups_ecb_node_t *node = &ecb->join.nodes[i];
        unsigned age = reclaim ? node->age : 0u;
        unsigned rank = 0u; /* the first of the highest rank wins */
        if (node->txnode == 0xFFu) {
            rank = 0x400u;
        } else if (node->flags == UPS_ECB__LAPSED) {
            rank = 0x300u + age;
        } else if (reclaim && node->flags == (UPS_ECB__HELD | UPS_ECB__PROBATION)) {
            rank = 0x2FFu - node->txnode; /* the lowest TxNode: as if adopted earliest */
        } else if (node->flags == UPS_ECB__HELD && age >= UPS_ECB__LEASE_AGE) {
            rank = 0x100u + age; /* offered: a node's own, in use */
        }
        if (rank > best) {
            best = rank;
            slot = i;
        }
    }
    return slot;
}

/** An entry for @p node_id, which has none, with a TxNode of its own: an unused one, the
 *  oldest lapsed Offer's, the lowest on probation's or the one silent longest past the lease
 *  (reclaimed). Else UPS_ECB__NO_SLOT and TxNodesFull. */
static int new_entry(ups_ecb_t *ecb, const uint8_t *node_id)
{
    int slot = vacant_entry(ecb, 1);
    if (slot == UPS_ECB__NO_SLOT) {
        ups_ecb__count(&ecb->counters.refused);
        ups_ecb__count(&ecb->counters.nodes_full);
        ups_ecb__send8(ecb, (OP_STATUS << 12) | (ST_TXNODES_FULL << 8), node_id);
        return UPS_ECB__NO_SLOT;
    }
    ups_ecb_node_t *node = &ecb->join.nodes[slot];
    unsigned txnode = node->txnode;
    if (node->flags & UPS_ECB__HELD) { /* reclaimed: the new node id takes its TxNode */
        ups_ecb__bind_forget(ecb, slot); /* its old owner is forgotten for good */
        ups_ecb__count(&ecb->counters.reclaimed);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    } else { /* the lowest TxNode no other entry uses: entries <= 127 TxNodes, one is free */
        uint8_t used[UPS_ECB_NODES]; /* in one pass, not one per TxNode (a census storm on a
                                        full bus finds several ids in a tick): the others use
                                        fewer TxNodes than UPS_ECB_NODES, one below is free */
        ups_ecb__copy(used, NULL, UPS_ECB_NODES);
        for (int i = 0; i < UPS_ECB_NODES; i++) {
            unsigned t = ecb->join.nodes[i].txnode; /* 0xFF in an unused entry */
            if (i != slot && t < UPS_ECB_NODES) {
                used[t] = 1u;
            }
        }
        for (txnode = 0u; txnode < UPS_ECB_NODES && used[txnode]; txnode++) {
        }
    }
    set_entry(node, node_id, txnode, 0u);
    return slot;
}

/** Entry @p node is unused from now on (its TxNode free again). */
static void forget(ups_ecb_node_t *node)
{
    node->txnode = 0xFFu;
    node->flags = 0u;
}

static void send_assign(ups_ecb_t *ecb, unsigned txnode, const uint8_t *node_id, unsigned offer)
{
    ups_ecb__send8(ecb, (OP_ASSIGN << 12) | offer | txnode, node_id);
}

/** Entry @p slot's node claimed (or is moved to) its TxNode: hold it (durable: noted, so that
 *  the application saves before it sends the Assign), with @p flags more (move), then Assign.
 *  One held already keeps its probation (a joiner's own was cleared by its CLAIM, in
 *  ups_ecb__join_seen). */
static void assign(ups_ecb_t *ecb, int slot, unsigned flags)
{
    ups_ecb_node_t *node = &ecb->join.nodes[slot];
    if (node->flags & UPS_ECB__HELD) {
        ups_ecb__bind_rejoined(ecb, slot); /* a (re)joining node starts with no channels */
    } else {
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    }
    node->flags = (uint8_t)(UPS_ECB__HELD | (node->flags & UPS_ECB__PROBATION) | flags);
    node->age = 0u;
    ups_ecb__count(&ecb->counters.joined);
    send_assign(ecb, node->txnode, node->node_id, 0u);
}

/** Give the node of @p node_id and entry @p slot (UPS_ECB__NO_SLOT: none) whose TxNode another
 *  holds (or that was told to move) one of its own: the one it holds, else a new one, with
 *  @p flags (UPS_ECB__PROBATION: a stray's id that held none, in a later window). */
static void move(ups_ecb_t *ecb, int slot, const uint8_t *node_id, unsigned flags)
{
    if (slot == UPS_ECB__NO_SLOT || !(ecb->join.nodes[slot].flags & UPS_ECB__HELD)) {
        if (slot != UPS_ECB__NO_SLOT) {
            forget(&ecb->join.nodes[slot]); /* offered or lapsed elsewhere */
        }
        slot = new_entry(ecb, node_id);
    }
    if (slot != UPS_ECB__NO_SLOT) {
        assign(ecb, slot, flags);
    }
}

/** The census found @p node_id: offer it a TxNode, which its node must claim. */
static void found(ups_ecb_t *ecb, const uint8_t *node_id)
{
    int slot = entry_of(ecb, node_id);
    if (slot != UPS_ECB__NO_SLOT && ecb->join.nodes[slot].flags == UPS_ECB__LAPSED) {
        ups_ecb_node_t *node = &ecb->join.nodes[slot];
        node->flags = 0u; /* offered the same TxNode again, unless it went to another */
        if (!free_for(ecb, node->txnode, slot)) {
            forget(node); /* then a TxNode of its own */
            slot = UPS_ECB__NO_SLOT;
        }
    }
    if (slot == UPS_ECB__NO_SLOT) {
        slot = new_entry(ecb, node_id);
        if (slot == UPS_ECB__NO_SLOT) {
            return;
        }
    }
    ups_ecb_node_t *node = &ecb->join.nodes[slot];
    node->flags = (uint8_t)(node->flags | UPS_ECB__OFFERED);
    ecb->join.t_offer[slot] = (uint16_t)ecb->now;
    send_assign(ecb, node->txnode, node_id, OFFER_BIT);
}

/** Count the entries' ages up to now, in 64ths of the lease; Offers unclaimed past the offer
 *  time (twice the slack @p s, at least OFFER_TIMEOUT) lapse: a lapsed one is remembered for
 *  a late claim. */
static void age_entries(ups_ecb_t *ecb, uint32_t s)
{
    ups_ecb_join_t *join = &ecb->join;
    uint32_t wait = 2u * s;
    if (wait < OFFER_TIMEOUT) {
        wait = OFFER_TIMEOUT;
    }
    uint32_t unit = ecb->cfg.lease_s * 1000u / UPS_ECB__LEASE_AGE; /* >= 15 ms */
    uint32_t rest;
    uint32_t steps = ups_ecb__div32(ups_ecb__since(ecb->now, join->t_aged), unit, &rest);
    join->t_aged = ecb->now - rest; /* counted up to the last whole unit */
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ups_ecb_node_t *node = &join->nodes[i];
        uint32_t age = node->age + steps;
        node->age = (uint8_t)(age > 255u ? 255u : age);
        if ((node->flags & UPS_ECB__OFFERED) &&
            ups_ecb__since16(ecb->now, join->t_offer[i]) >= wait) {
            ups_ecb__count(&ecb->counters.offers_withdrawn);
            if (node->flags & UPS_ECB__HELD) {
                node->flags &= (uint8_t)~UPS_ECB__OFFERED; /* on probation still, if it was */
            } else {
                node->flags = UPS_ECB__LAPSED;
                node->age = 0u;
            }
        }
    }
}

/** A CLAIM of @p txnode by @p node_id (docs/protocol.md, *Joining* and *Restarts*). Returns 1
 *  when it is a request from a TxNode nobody holds, which the dispatcher handles as such. */
static int on_claim(ups_ecb_t *ecb, unsigned txnode, const uint8_t *node_id)
{
    unsigned flags = 0u; /* of the TxNode it is moved to */
    int slot = entry_of(ecb, node_id);
    ups_ecb_node_t *node = slot != UPS_ECB__NO_SLOT ? &ecb->join.nodes[slot] : NULL;
    if (node != NULL && node->txnode == txnode) {
        if (node->flags == UPS_ECB__LAPSED) {
            ups_ecb__count(&ecb->counters.late_claims); /* slow to claim what it was offered */
        }
        if (node->flags != UPS_ECB__LAPSED || free_for(ecb, txnode, slot)) {
            if (node->flags != UPS_ECB__HELD) { /* a joiner takes the TxNode offered */
                assign(ecb, slot, 0u);
            }
            return 0;
        } /* else given to another meanwhile: a TxNode of its own */
    } else {
        int known = (node != NULL && (node->flags & UPS_ECB__HELD)) ? (int)node->txnode : -1;
        int holder = ups_ecb__holder(ecb, txnode);
        /* claims answer Hello (later windows: strays only); any other is stray or forged */
        int window = ecb->recovering && (!ecb->started_up || ups_ecb__stray(ecb, txnode));
        if (window && known < 0 && holder == UPS_ECB__NO_SLOT) { /* adopt */
            if (node == NULL) {
                slot = vacant_entry(ecb, 0);
                if (slot == UPS_ECB__NO_SLOT) {
                    ups_ecb__count(&ecb->counters.nodes_full);
                    return 0;
                }
                node = &ecb->join.nodes[slot];
            }
            /* an entry of another node that lapsed or is offered this TxNode gives it up */
            for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
                if (ecb->join.nodes[i].txnode == txnode) {
                    forget(&ecb->join.nodes[i]);
                }
            }
            ups_ecb__count(&ecb->counters.adopted);
            /* a stray's (a later window): on probation until a frame of its TxNode comes after
               this CLAIM (ups_ecb__join_seen ran before it: it does not clear this) */
            set_entry(node, node_id, txnode,
                      ecb->started_up ? UPS_ECB__HELD | UPS_ECB__PROBATION : UPS_ECB__HELD);
            ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
            return 0;
        }
        ups_ecb__count(&ecb->counters.conflicts);
        if (!window) {
            if (!ecb->recovering && holder == UPS_ECB__NO_SLOT) {
                if (known >= 0) { /* told to move: the truth */
                    send_assign(ecb, (unsigned)known, node_id, 0u);
                } else {
                    return 1;
                }
            }
            return 0;
        } /* else another's TxNode: the holder keeps it. An id that held none is a stray's in a
             later window: its new TxNode is on probation, as an adopted one is (a flood of
             CLAIMs of one TxNode by made-up ids would take every entry otherwise) */
        if (ecb->started_up && known < 0) {
            flags = UPS_ECB__PROBATION;
        }
    }
    move(ecb, slot, node_id, flags);
    return 0;
}

/* ==== the census ========================================================================== */

/** How much longer than usual the census waits for answers now: 1.5 times the lateness of the
 *  latest late answer, halving every 2 s since (linearly between halvings), 0 below 30 ms. */
static uint32_t slack(const ups_ecb_t *ecb)
{
    const ups_ecb_join_t *join = &ecb->join;
    if (join->slack0 == 0u) {
        return 0u;
    }
    uint32_t age = ups_ecb__since(ecb->now, join->late_at);
    uint32_t part;
    uint32_t halvings = ups_ecb__div32(age, SLACK_HALF_LIFE, &part);
    if (halvings >= 16u) {
        return 0u;
    }
    uint32_t s = (uint32_t)join->slack0 >> halvings;
    s -= ups_ecb__div32(s * part, 2u * SLACK_HALF_LIFE, &part);
    return s < FIRST_MIN ? 0u : s;
}

/** An answer came @p delay ms after its query was sent, which had closed. */
static void late(ups_ecb_t *ecb, uint32_t delay)
{
    /* 1.5 times the delay, at most SLACK_MAX (which 2667 ms and more reach) */
    uint32_t s = delay > SLACK_MAX * 2u / 3u ? SLACK_MAX : delay + delay / 2u;
    if (s > slack(ecb)) {
        ecb->join.slack0 = (uint16_t)s;
        ecb->join.late_at = ecb->now;
    }
}

int ups_ecb__join_busy(const ups_ecb_t *ecb)
{
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        if ((ecb->join.queries[i].tag & Q_STATE) == Q_OPEN) {
            return 1;
        }
    }
    return ecb->join.g_count != 0u;
}

/** The place of the @p i-th waiting group (i <= UPS_ECB__GROUPS) in the ring. */
static unsigned ring(const ups_ecb_join_t *join, unsigned i)
{
    unsigned at = join->g_head + i;
#if (UPS_ECB__GROUPS & (UPS_ECB__GROUPS - 1)) == 0 /* a power of 2: a mask */
    return at % UPS_ECB__GROUPS;
#else /* no division (Cortex-M0+ has none) */
    return at >= UPS_ECB__GROUPS ? at - UPS_ECB__GROUPS : at;
#endif
}

/** Query @p plen nibbles of @p prefix (a group of one) or its children in @p set in this
 *  census, unless it has sent all it may or no group is free (cut, counted). */
static void follow(ups_ecb_t *ecb, const uint8_t *prefix, unsigned plen, unsigned set,
                   unsigned tries)
{
    ups_ecb_join_t *join = &ecb->join;
    unsigned want = branches(set);
    unsigned queued = join->queued;
    unsigned room = queued >= MAX_QUERIES ? 0u : MAX_QUERIES - queued;
    if (join->g_count >= UPS_ECB__GROUPS) {
        room = 0u;
    }
    if (room < want) { /* the highest nibbles are cut */
        count_n(&ecb->counters.census_cut, want - room);
        if (room == 0u) {
            return;
        }
        for (unsigned n = 16u; n-- > 0u && want > room;) {
            if (set & (1u << n)) {
                set &= ~(1u << n);
                want--;
            }
        }
    }
    ups_ecb_group_t *group = &join->groups[ring(join, join->g_count)];
    join->g_count++;
    join->queued = (uint16_t)(queued + want);
    join->uncounted = (uint16_t)(join->uncounted + want);
    ups_ecb__copy(group->prefix, prefix, 8u);
    for (unsigned s = plen; s < NIBBLES; s++) { /* a Query's data: the prefix, then zeros */
        set_nibble(group->prefix, s, 0u);
    }
    group->plen = (uint8_t)plen;
    group->tries = (uint8_t)tries;
    group->set = (uint16_t)set;
}

static void start_census(ups_ecb_t *ecb)
{
    static const uint8_t none[8] = {0};
    ups_ecb_join_t *join = &ecb->join;
    ups_ecb__count(&ecb->counters.census_censuses);
    join->retries = 0u;
    join->queued = 0u; /* none waits: the census before is over */
    follow(ecb, none, 0u, 0u, 0u);
}

static void pump(ups_ecb_t *ecb);

/** A joiner asked: a census, or another one after the current one. */
static void knock(ups_ecb_t *ecb)
{
    ups_ecb__count(&ecb->counters.census_knocks);
    if (ups_ecb__join_busy(ecb)) {
        ecb->join.again = 1u;
        return;
    }
    start_census(ecb);
    pump(ecb);
}

/** Open @p query for @p epoch now: a window of its own from now on. */
static void open_query(ups_ecb_t *ecb, ups_ecb_query_t *query, unsigned epoch)
{
    query->tag = (uint8_t)(Q_OPEN | epoch);
    query->sent = ecb->now;
    query->last = ecb->now;
    query->many = 0u;
    query->seq = ecb->join.seq++;
}

/** A new open query, empty, of a free epoch (round robin, none open or in quarantine) in a
 *  free slot, else in the one closed longest past its quarantine; NULL when none. */
static ups_ecb_query_t *new_query(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    uint32_t q = slack(ecb) / 2u;
    if (q < QUARANTINE) {
        q = QUARANTINE;
    }
    unsigned busy = 0u; /* the epochs open or in quarantine */
    ups_ecb_query_t *best = NULL;
    uint32_t best_age = 0u;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        ups_ecb_query_t *query = &join->queries[i];
        uint32_t age = ups_ecb__since(ecb->now, query->last);
        if (query->tag == 0u) { /* free (the last free one) */
            best = query;
            best_age = 0xFFFFFFFFu;
        } else if ((query->tag & Q_STATE) == Q_OPEN || age < q) {
            busy |= 1u << (query->tag & 0x0Fu);
        } else if (age > best_age) { /* the first closed longest */
            best = query;
            best_age = age;
        }
    }
    for (unsigned k = 0; k < 16u && best != NULL; k++) {
        unsigned e = (join->next_epoch + k) % 16u;
        if (!(busy & (1u << e))) {
            join->next_epoch = (uint8_t)((e + 1u) % 16u);
            for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) { /* the epoch's old query is gone */
                if (join->queries[i].tag == (Q_CLOSED | e)) {
                    join->queries[i].tag = 0u;
                }
            }
            ups_ecb__copy((uint8_t *)best, NULL, (unsigned)sizeof(*best));
            open_query(ecb, best, e);
            return best;
        }
    }
    return NULL;
}

/** Send waiting queries while epochs are free; then another census if a Knock came. */
static void pump(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    ups_ecb_query_t *query;
again:
    while (join->g_count > 0u && (query = new_query(ecb)) != NULL) {
        ups_ecb_group_t *group = &join->groups[join->g_head];
        ups_ecb__copy(query->prefix, group->prefix, 8u);
        unsigned plen = group->plen;
        query->tries = group->tries; /* 0 in a group of children */
        if (group->set != 0u) { /* the lowest child of the group */
            unsigned n = 0;
            while (n < 15u && !(group->set & (1u << n))) {
                n++;
            }
            group->set = (uint16_t)(group->set & ~(1u << n));
            set_nibble(query->prefix, plen++, n);
        }
        if (join->g_counted == 0u) { /* the head's group is not counted yet */
            join->uncounted--;
        }
        if (group->set == 0u) {
            join->g_head = (uint8_t)ring(join, 1u);
            join->g_count--;
            if (join->g_counted > 0u) {
                join->g_counted--;
            }
        }
        query->plen = (uint8_t)plen;
        ups_ecb__count(&ecb->counters.census_queries);
        unsigned epoch = query->tag & 0x0Fu;
        if (plen == 0u) {
            ups_ecb__send8(ecb, (OP_STATUS << 12) | epoch, NULL); /* Census: status 0 */
        } else {
            unsigned field = (OP_QUERY << 12) | (epoch << 8) | ((plen - 1u) << 4) |
                             nibble_at(query->prefix, plen - 1u);
            ups_ecb__send8(ecb, field, query->prefix);
        }
    }
    count_n(&ecb->counters.queries_waiting, join->uncounted); /* the new branches that wait */
    join->uncounted = 0u;
    join->g_counted = join->g_count;
    if (!ups_ecb__join_busy(ecb) && join->again) {
        join->again = 0u; /* knock() again, as a loop (no recursion: a bounded stack) */
        ups_ecb__count(&ecb->counters.census_knocks);
        start_census(ecb);
        goto again;
    }
}

/** A Stage for the query its epoch last carried, which has closed: once the query's first
 *  stages came late, it was a joiner's late answer, and the census waits longer. */
static void late_stage(ups_ecb_t *ecb, ups_ecb_query_t *query, unsigned stage)
{
    uint32_t age = ups_ecb__since(ecb->now, query->sent);
    if (age > LONGEST + SLACK_MAX || stage < query->plen) {
        return;
    }
    query->many = (uint16_t)(query->many | (1u << stage)); /* closed: its late answers */
    unsigned wanted = (((1u << LATE_QUORUM) - 1u) << query->plen) & 0xFFFFu; /* or to the end */
    if ((query->many & wanted) == wanted) {
        query->many = 0u;
        late(ecb, age);
    }
}

static void on_stage(ups_ecb_t *ecb, unsigned epoch, unsigned stage, unsigned nibble)
{
    ups_ecb_join_t *join = &ecb->join;
    ups_ecb_query_t *query = NULL; /* the query the epoch carries (one at most), or last did */
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        if (join->queries[i].tag != 0u && (join->queries[i].tag & 0x0Fu) == epoch) {
            query = &join->queries[i];
        }
    }
    if (query != NULL && (query->tag & Q_STATE) == Q_CLOSED) {
        if (query->present != 0u || stage < query->plen) {
            ups_ecb__count(&ecb->counters.census_late_stages);
            late_stage(ecb, query, stage);
            return;
        }
        ups_ecb__count(&ecb->counters.census_reopened); /* its answers come late, not never */
        late(ecb, ups_ecb__since(ecb->now, query->sent));
        open_query(ecb, query, epoch);
    }
    if (query == NULL || stage < query->plen) {
        ups_ecb__count(&ecb->counters.census_late_stages);
        return;
    }
    ups_ecb__count(&ecb->counters.census_stages);
    if (query->present == 0u) { /* its first answer: the round trip */
        uint32_t d = ups_ecb__since(ecb->now, query->sent);
        int32_t rtt = (int32_t)join->rtt;
        rtt += ((int32_t)(d > 60000u ? 60000u : d) - rtt) / 4; /* >= 3/4 rtt: >= 0 */
        join->rtt = (uint16_t)rtt;
    }
    unsigned bit = 1u << stage;
    if (!(query->present & bit)) {
        query->present = (uint16_t)(query->present | bit);
        set_nibble(query->prefix, stage, nibble);
    } else if (nibble_at(query->prefix, stage) != nibble || (query->many & bit)) {
        if (!(query->many & (bit - 1u))) { /* the first stage with several: its nibbles */
            if (!(query->many & bit)) {
                query->set = (uint16_t)(1u << nibble_at(query->prefix, stage));
            }
            query->set = (uint16_t)(query->set | (1u << nibble));
        }
        query->many = (uint16_t)(query->many | bit);
    }
    query->last = ecb->now;
}

/** Read a closed query's answers (docs/protocol.md, *Joining*). */
static void conclude(ups_ecb_t *ecb, const ups_ecb_query_t *query)
{
    if (query->present == 0u) { /* nobody has this prefix (any more) */
        return;
    }
    uint8_t prefix[8]; /* its prefix and the nibbles heard: the first len are certain */
    ups_ecb__copy(prefix, query->prefix, 8u);
    unsigned len = query->plen;
    unsigned certain = query->present & ~(unsigned)query->many; /* one nibble heard */
    while (len < NIBBLES && (certain & (1u << len))) {
        len++;
    }
    if ((~query->present & 0xFFFFu) >> query->plen) { /* incomplete: ask again what is certain */
        ups_ecb__count(&ecb->counters.census_incomplete);
        unsigned tries = (len == query->plen ? query->tries : 0u) + 1u;
        if (tries <= RETRIES && ecb->join.retries < RETRY_BUDGET) {
            ecb->join.retries++;
            ups_ecb__count(&ecb->counters.census_retries);
            follow(ecb, prefix, len, 0u, tries);
        }
        return;
    }
    if (len < NIBBLES - 1u) { /* several joiners: a query for each branch */
        follow(ecb, prefix, len, query->set, 0u);
        return;
    }
    /* whole ids: one, or several at the last stage at once */
    unsigned set = len == NIBBLES ? 1u << nibble_at(prefix, NIBBLES - 1u) : query->set;
    for (unsigned n = 0; n < 16u; n++) {
        if (set & (1u << n)) {
            set_nibble(prefix, NIBBLES - 1u, n);
            found(ecb, prefix);
        }
    }
}

/** Close the due queries and read them; send what waits. @p s: the slack now. */
static void census_tick(ups_ecb_t *ecb, uint32_t s)
{
    ups_ecb_join_t *join = &ecb->join;
    uint32_t first = 4u * join->rtt;
    first = first < FIRST_MIN ? FIRST_MIN : (first > FIRST_MAX ? FIRST_MAX : first);
    first = first > s ? first : s;
    uint32_t quiet = s / 4u > QUIET ? s / 4u : QUIET;
    join->slack0 = (uint16_t)(s == 0u ? 0u : join->slack0);
    for (unsigned k = 0; k < UPS_ECB_QUERIES; k++) { /* the due queries, in the order opened */
        ups_ecb_query_t *next = NULL;
        for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
            ups_ecb_query_t *query = &join->queries[i];
            if ((query->tag & Q_STATE) == Q_CLOSED) { /* closed ones may stay for weeks */
                (void)ups_ecb__age(ecb->now, &query->sent);
                (void)ups_ecb__age(ecb->now, &query->last);
            }
            uint32_t age = ups_ecb__since(ecb->now, query->sent);
            int due = (age >= first && ups_ecb__since(ecb->now, query->last) >= quiet) ||
                      age >= LONGEST + s;
            if ((query->tag & Q_STATE) == Q_OPEN && due &&
                (next == NULL || (int16_t)(uint16_t)(query->seq - next->seq) < 0)) {
                next = query;
            }
        }
        if (next == NULL) {
            break;
        }
        next->tag = (uint8_t)(next->tag + (Q_CLOSED - Q_OPEN)); /* closed, in its epoch */
        next->last = ecb->now;
        conclude(ecb, next);
        next->many = 0u; /* closed: its late answers, none yet */
    }
    pump(ecb);
}

/* ==== the join's frames =================================================================== */

int ups_ecb__join_rx(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    (void)len;
    unsigned txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned field = id & UPS_ECB__ETAG_MASK;
    if (txnode != UPS_ECB__MGMT) { /* CLAIM */
        return on_claim(ecb, txnode, data);
    }
    if (field >> 12 == 0u) { /* Stage */
        if (!ecb->recovering) {
            on_stage(ecb, (field >> 8) & 0xFu, (field >> 4) & 0xFu, field & 0xFu);
        }
    } else if (ecb->recovering) { /* Knock (the dispatcher sends no other) */
        ecb->knocked = 1u; /* answered when the recovery window ends */
    } else {
        knock(ecb);
    }
    return 0;
}

void ups_ecb__join_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data)
{
    if ((id >> UPS_ECB__PRIO_SHIFT) != 0u) { /* a Bind (priority 1): the binding's to correct */
        return;
    }
    unsigned field = id & UPS_ECB__ETAG_MASK;
    unsigned row = field >> 8; /* op and status (an Assign's: 0) */
    int slot = entry_of(ecb, data);
    if (slot == UPS_ECB__NO_SLOT) {
        return;
    }
    const ups_ecb_node_t *node = &ecb->join.nodes[slot];
    unsigned flags = node->flags;
    if (row == OP_ASSIGN << 4) { /* Assign of an id the table gives another */
        if ((field & OFFER_BIT) || node->txnode == (field & 0x7Fu)) {
            return;
        }
        flags &= UPS_ECB__HELD;
    } else if (row != ((OP_STATUS << 4) | ST_TXNODES_FULL) &&
               row != ((OP_STATUS << 4) | ST_FAILED)) {
        return;
    }
    if (flags & (UPS_ECB__HELD | UPS_ECB__OFFERED)) { /* the table's answer again */
        ups_ecb__count(&ecb->counters.conflicts);
        send_assign(ecb, node->txnode, data, (flags & UPS_ECB__HELD) ? 0u : OFFER_BIT);
    }
}

void ups_ecb__join_tick(ups_ecb_t *ecb)
{
    uint32_t s = slack(ecb);
    age_entries(ecb, s);
    census_tick(ecb, s);
}

void ups_ecb__join_stop(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        join->queries[i].tag = 0u;
    }
    join->g_count = 0u;
    join->g_counted = 0u;
    join->uncounted = 0u;
    join->again = 0u;
}

void ups_ecb__join_recovered(ups_ecb_t *ecb)
{
    if (ecb->knocked) {
        ecb->knocked = 0u;
        knock(ecb);
    }
}

/* ==== the blob's section: per held entry, its index, its TxNode and its id (10 bytes) ===== */

#define ENTRY_BYTES 10u

size_t ups_ecb__join_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    size_t n = 0;
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        const ups_ecb_node_t *node = &ecb->join.nodes[i];
        if (!(node->flags & UPS_ECB__HELD)) {
            continue;
        }
        if (n + ENTRY_BYTES > cap) {
            return 0u;
        }
        out[n] = (uint8_t)i;
        out[n + 1u] = node->txnode;
        ups_ecb__copy(&out[n + 2u], node->node_id, 8u);
        n += ENTRY_BYTES;
    }
    return n;
}

int ups_ecb__join_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size)
{
    size_t n = 0;
    for (; n + ENTRY_BYTES <= size; n += ENTRY_BYTES) { /* each entry once: <= UPS_ECB_NODES */
        unsigned slot = in[n];
        unsigned txnode = in[n + 1u];
        if (slot >= UPS_ECB_NODES || txnode >= TXNODES ||
            ecb->join.nodes[slot].txnode != 0xFFu || ups_ecb__holder(ecb, txnode) >= 0 ||
            entry_of(ecb, &in[n + 2u]) >= 0) {
            return UPS_ERR_ARGUMENT; /* out of range, or twice: not a blob this library wrote */
        }
        set_entry(&ecb->join.nodes[slot], &in[n + 2u], txnode, UPS_ECB__HELD);
    }
    return n == size ? UPS_OK : UPS_ERR_ARGUMENT; /* no part of an entry */
}
