/*
 * libups-ecb: TxNodes by node id, the census (Knock, Census, Query, Stage), Offers, CLAIM,
 * Assign, moves, TxNodesFull (docs/protocol.md, *Joining* and *Restarts*; broker/_census.py and
 * broker/_txnodes.py are the same in Python).
 *
 * The node table holds every node id the CAN-ECB knows: held (durable), offered, or lapsed
 * (an Offer nobody claimed in time, kept for a late claim). A new node id takes an unused
 * entry, else the one of the oldest lapsed Offer, else the entry of the TxNode silent longest
 * past the lease (reclaimed); else TxNodesFull. Its TxNode is the lowest no entry uses (the
 * reclaimed one's when reclaimed). The Python CAN-ECB keeps up to 127 lapsed Offers beside
 * 127 TxNodes; here they share the UPS_ECB_NODES entries and give way first.
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
#define Q_FREE 0u
#define Q_OPEN 1u
#define Q_CLOSED 2u

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
#define ST_KNOCK 0xFu
#define OFFER_BIT 0x80u
#define CLAIM 0x0004u

static unsigned nibble_at(const uint8_t *id, unsigned s)
{
    return (s & 1u) ? (id[s / 2u] & 0x0Fu) : (unsigned)(id[s / 2u] >> 4);
}

static void set_nibble(uint8_t *id, unsigned s, unsigned n)
{
    if (s & 1u) {
        id[s / 2u] = (uint8_t)((id[s / 2u] & 0xF0u) | (n & 0x0Fu));
    } else {
        id[s / 2u] = (uint8_t)((id[s / 2u] & 0x0Fu) | ((n & 0x0Fu) << 4));
    }
}

static unsigned popcount16(unsigned v)
{
    unsigned n = 0;
    for (; v != 0u; v &= v - 1u) {
        n++;
    }
    return n;
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

/** Whether any entry but @p except uses @p txnode (held, offered or lapsed). */
static int txnode_used(const ups_ecb_t *ecb, unsigned txnode, int except)
{
    return with_txnode(ecb, txnode, except, 0u) != UPS_ECB__NO_SLOT;
}

/** Nobody else holds @p txnode, and it is offered to nobody but entry @p slot. */
static int free_for(const ups_ecb_t *ecb, unsigned txnode, int slot)
{
    return with_txnode(ecb, txnode, slot, UPS_ECB__HELD | UPS_ECB__OFFERED) == UPS_ECB__NO_SLOT;
}

/** Count the entries' ages up to now, in 64ths of the lease. */
static void age_entries(ups_ecb_t *ecb)
{
    uint32_t unit = ecb->cfg.lease_s * 1000u / UPS_ECB__LEASE_AGE; /* >= 15 ms */
    uint32_t rest;
    uint32_t steps = ups_ecb__div32(ups_ecb__since(ecb->now, ecb->join.t_aged), unit, &rest);
    if (steps == 0u) {
        return;
    }
    ecb->join.t_aged += steps * unit;
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ups_ecb_node_t *node = &ecb->join.nodes[i];
        node->age = (uint8_t)(node->age + steps > 255u ? 255u : node->age + steps);
    }
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
    }
}

/** An entry for @p node_id, which has none, with a TxNode of its own: an unused one, the
 *  oldest lapsed Offer's, or the one silent longest past the lease (reclaimed). Else
 *  UPS_ECB__NO_SLOT and TxNodesFull. */
static int new_entry(ups_ecb_t *ecb, const uint8_t *node_id)
{
    ups_ecb_join_t *join = &ecb->join;
    int slot = UPS_ECB__NO_SLOT;
    int lapsed = UPS_ECB__NO_SLOT;
    int idle = UPS_ECB__NO_SLOT;
    unsigned lapsed_age = 0u;
    unsigned idle_age = 0u;
    for (int i = 0; i < UPS_ECB_NODES && slot == UPS_ECB__NO_SLOT; i++) {
        ups_ecb_node_t *node = &join->nodes[i];
        if (node->txnode == 0xFFu) {
            slot = i;
        } else if (node->flags == UPS_ECB__LAPSED) {
            unsigned age = node->age;
            if (lapsed == UPS_ECB__NO_SLOT || age > lapsed_age) {
                lapsed = i;
                lapsed_age = age;
            }
        } else if (node->flags == UPS_ECB__HELD) { /* offered: a node's own, in use */
            unsigned age = node->age;
            if (idle == UPS_ECB__NO_SLOT || age > idle_age) {
                idle = i;
                idle_age = age;
            }
        }
    }
    unsigned txnode = 0xFFu;
    if (slot == UPS_ECB__NO_SLOT && lapsed != UPS_ECB__NO_SLOT) {
        slot = lapsed;
        join->nodes[slot].txnode = 0xFFu; /* its TxNode is free again */
    } else if (slot == UPS_ECB__NO_SLOT && idle != UPS_ECB__NO_SLOT &&
               idle_age >= UPS_ECB__LEASE_AGE) {
        slot = idle;
        txnode = join->nodes[slot].txnode;
        ups_ecb__bind_forget(ecb, slot); /* its old owner is forgotten for good */
        ups_ecb__count(&ecb->counters.reclaimed);
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    }
    if (slot == UPS_ECB__NO_SLOT) {
        ups_ecb__count(&ecb->counters.refused);
        ups_ecb__count(&ecb->counters.nodes_full);
        ups_ecb__send8(ecb, (OP_STATUS << 12) | (ST_TXNODES_FULL << 8), node_id);
        return UPS_ECB__NO_SLOT;
    }
    for (unsigned t = 0; txnode == 0xFFu && t < TXNODES; t++) {
        if (!txnode_used(ecb, t, slot)) {
            txnode = t;
        }
    }
    ups_ecb_node_t *node = &join->nodes[slot];
    ups_ecb__copy(node->node_id, node_id, 8u);
    node->txnode = (uint8_t)txnode; /* entries <= 127 TxNodes: one is always free */
    node->flags = 0u;
    node->age = 0u;
    return slot;
}

/** The entry of @p node_id with its own TxNode: the one it holds, else a new one. */
static int txnode_for(ups_ecb_t *ecb, const uint8_t *node_id)
{
    int slot = entry_of(ecb, node_id);
    if (slot != UPS_ECB__NO_SLOT && (ecb->join.nodes[slot].flags & UPS_ECB__HELD)) {
        return slot;
    }
    if (slot != UPS_ECB__NO_SLOT) { /* offered or lapsed elsewhere: its own TxNode now */
        ecb->join.nodes[slot].txnode = 0xFFu;
        ecb->join.nodes[slot].flags = 0u;
    }
    return new_entry(ecb, node_id);
}

static void send_assign(ups_ecb_t *ecb, unsigned txnode, const uint8_t *node_id, int offer)
{
    ups_ecb__send8(ecb, (OP_ASSIGN << 12) | (offer ? OFFER_BIT : 0u) | txnode, node_id);
}

/** Entry @p slot's node claimed (or is moved to) @p txnode: hold it (durable: noted, so that
 *  the application saves before it sends the Assign), then Assign. */
static void assign(ups_ecb_t *ecb, int slot, unsigned txnode)
{
    ups_ecb_node_t *node = &ecb->join.nodes[slot];
    if ((node->flags & UPS_ECB__HELD) && node->txnode == txnode) {
        ups_ecb__bind_rejoined(ecb, slot); /* a (re)joining node starts with no channels */
    } else {
        if (node->flags & UPS_ECB__HELD) {
            ups_ecb__bind_rejoined(ecb, slot);
        }
        node->txnode = (uint8_t)txnode;
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
    }
    node->flags = UPS_ECB__HELD;
    node->age = 0u;
    ups_ecb__count(&ecb->counters.joined);
    send_assign(ecb, txnode, node->node_id, 0);
}

/** Give a node whose TxNode another holds (or that was told to move) one of its own. */
static void move(ups_ecb_t *ecb, const uint8_t *node_id)
{
    int slot = txnode_for(ecb, node_id);
    if (slot != UPS_ECB__NO_SLOT) {
        assign(ecb, slot, ecb->join.nodes[slot].txnode);
    }
}

/** The census found @p node_id: offer it a TxNode, which its node must claim. */
static void found(ups_ecb_t *ecb, const uint8_t *node_id)
{
    if (ecb->elect.role == UPS_ECB_STANDBY) {
        return;
    }
    int slot = entry_of(ecb, node_id);
    if (slot != UPS_ECB__NO_SLOT && ecb->join.nodes[slot].flags == UPS_ECB__LAPSED) {
        if (free_for(ecb, ecb->join.nodes[slot].txnode, slot)) {
            ecb->join.nodes[slot].flags = 0u; /* offered the same TxNode again */
        } else {
            slot = txnode_for(ecb, node_id);
        }
    } else if (slot == UPS_ECB__NO_SLOT) {
        slot = new_entry(ecb, node_id);
    }
    if (slot == UPS_ECB__NO_SLOT) {
        return;
    }
    ups_ecb_node_t *node = &ecb->join.nodes[slot];
    node->flags = (uint8_t)(node->flags | UPS_ECB__OFFERED);
    node->t_offer = (uint16_t)ecb->now;
    send_assign(ecb, node->txnode, node->node_id, 1);
}

static uint32_t slack(const ups_ecb_t *ecb);

/** Offers unclaimed past the offer time lapse; a lapsed one is remembered for a late claim. */
static void lapse_offers(ups_ecb_t *ecb)
{
    uint32_t wait = 2u * slack(ecb);
    if (wait < OFFER_TIMEOUT) {
        wait = OFFER_TIMEOUT;
    }
    age_entries(ecb);
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ups_ecb_node_t *node = &ecb->join.nodes[i];
        if ((node->flags & UPS_ECB__OFFERED) && ups_ecb__since16(ecb->now, node->t_offer) >= wait) {
            ups_ecb__count(&ecb->counters.offers_withdrawn);
            if (node->flags & UPS_ECB__HELD) {
                node->flags = UPS_ECB__HELD;
            } else {
                node->flags = UPS_ECB__LAPSED;
                node->age = 0u;
            }
        }
    }
}

static void on_claim(ups_ecb_t *ecb, unsigned txnode, const uint8_t *node_id)
{
    int slot = entry_of(ecb, node_id);
    ups_ecb_node_t *node = slot != UPS_ECB__NO_SLOT ? &ecb->join.nodes[slot] : NULL;
    if (node != NULL && node->txnode == txnode && (node->flags & UPS_ECB__OFFERED)) {
        assign(ecb, slot, txnode); /* a joiner takes the TxNode offered */
        return;
    }
    if (node != NULL && node->txnode == txnode && node->flags == UPS_ECB__LAPSED) {
        ups_ecb__count(&ecb->counters.late_claims); /* slow to claim what it was offered */
        if (free_for(ecb, txnode, slot)) {
            assign(ecb, slot, txnode);
        } else { /* given to another meanwhile: a TxNode of its own */
            move(ecb, node_id);
        }
        return;
    }
    int known = (node != NULL && (node->flags & UPS_ECB__HELD)) ? (int)node->txnode : -1;
    if (known == (int)txnode) {
        return;
    }
    int holder = ups_ecb__holder(ecb, txnode);
    if (!ecb->recovering) { /* claims answer Hello; any other is stray or forged */
        ups_ecb__count(&ecb->counters.conflicts);
        if (known >= 0 && holder == UPS_ECB__NO_SLOT) { /* told to move: the truth */
            send_assign(ecb, (unsigned)known, node_id, 0);
        } else if (known < 0 && holder == UPS_ECB__NO_SLOT) {
            ups_ecb__unassigned(ecb, txnode);
        }
        return;
    }
    if (ecb->started_up && !ups_ecb__stray(ecb, txnode)) { /* later windows: strays only */
        ups_ecb__count(&ecb->counters.conflicts);
        return;
    }
    if (known < 0 && holder == UPS_ECB__NO_SLOT) { /* adopt */
        if (node == NULL) {
            int free_slot = with_txnode(ecb, 0xFFu, UPS_ECB__NO_SLOT, 0u); /* unused */
            for (int i = 0; i < UPS_ECB_NODES && free_slot == UPS_ECB__NO_SLOT; i++) {
                if (ecb->join.nodes[i].flags == UPS_ECB__LAPSED) {
                    free_slot = i;
                }
            }
            if (free_slot == UPS_ECB__NO_SLOT) {
                ups_ecb__count(&ecb->counters.nodes_full);
                return;
            }
            node = &ecb->join.nodes[free_slot];
            ups_ecb__copy(node->node_id, node_id, 8u);
        }
        /* an entry of another node that lapsed or is offered this TxNode gives it up */
        for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
            ups_ecb_node_t *other = &ecb->join.nodes[i];
            if (other != node && other->txnode == txnode) {
                other->txnode = 0xFFu;
                other->flags = 0u;
            }
        }
        ups_ecb__count(&ecb->counters.adopted);
        node->txnode = (uint8_t)txnode;
        node->flags = UPS_ECB__HELD;
        node->age = 0u;
        ups_ecb__note(ecb, UPS_ECB_NOTE_STATE);
        return;
    }
    ups_ecb__count(&ecb->counters.conflicts); /* another's TxNode: the holder keeps it */
    move(ecb, node_id);
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
    uint32_t s = delay > SLACK_MAX ? SLACK_MAX : delay + delay / 2u;
    if (s > SLACK_MAX) {
        s = SLACK_MAX;
    }
    if (s > slack(ecb)) {
        ecb->join.slack0 = (uint16_t)s;
        ecb->join.late_at = ecb->now;
    }
}

int ups_ecb__join_busy(const ups_ecb_t *ecb)
{
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        if (ecb->join.queries[i].state == Q_OPEN) {
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

static unsigned waiting_branches(const ups_ecb_join_t *join)
{
    unsigned n = 0;
    for (unsigned i = 0; i < join->g_count; i++) {
        unsigned set = join->groups[ring(join, i)].set;
        n += set != 0u ? popcount16(set) : 1u;
    }
    return n;
}

/** Query @p plen nibbles of @p prefix (a group of one) or its children in @p set in this
 *  census, unless it has sent all it may or no group is free (cut, counted). */
static void follow(ups_ecb_t *ecb, const uint8_t *prefix, unsigned plen, unsigned set,
                   unsigned tries)
{
    ups_ecb_join_t *join = &ecb->join;
    unsigned want = set != 0u ? popcount16(set) : 1u;
    unsigned queued = join->sent + waiting_branches(join);
    unsigned room = queued >= MAX_QUERIES ? 0u : MAX_QUERIES - queued;
    if (join->g_count >= UPS_ECB__GROUPS) {
        room = 0u;
    }
    if (room < want) { /* the highest nibbles are cut */
        unsigned cut = want - room;
        for (unsigned k = 0; k < cut; k++) {
            ups_ecb__count(&ecb->counters.census_cut);
        }
        if (room == 0u) {
            return;
        }
        for (unsigned n = 16u; n-- > 0u && cut > 0u;) {
            if (set & (1u << n)) {
                set &= ~(1u << n);
                cut--;
            }
        }
    }
    ups_ecb_group_t *group = &join->groups[ring(join, join->g_count)];
    join->g_count++;
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
    join->sent = 0u;
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

static uint32_t quarantine(const ups_ecb_t *ecb)
{
    uint32_t q = slack(ecb) / 2u;
    return q > QUARANTINE ? q : QUARANTINE;
}

/** A free epoch (round robin, none open or in quarantine) and a slot for its query (a free
 *  one, else the one closed longest past its quarantine); 0 when none. */
static int take_epoch(ups_ecb_t *ecb, unsigned *epoch, unsigned *slot)
{
    ups_ecb_join_t *join = &ecb->join;
    uint32_t q = quarantine(ecb);
    int best = -1;
    uint32_t best_age = 0u;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        ups_ecb_query_t *query = &join->queries[i];
        if (query->state == Q_FREE) {
            best = (int)i;
            best_age = 0xFFFFFFFFu;
        } else if (query->state == Q_CLOSED) {
            uint32_t age = ups_ecb__since(ecb->now, query->last);
            if (age >= q && (best < 0 || age > best_age)) {
                best = (int)i;
                best_age = age;
            }
        }
    }
    if (best < 0) {
        return 0;
    }
    for (unsigned k = 0; k < 16u; k++) {
        unsigned e = (join->next_epoch + k) % 16u;
        int busy = 0;
        for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
            const ups_ecb_query_t *query = &join->queries[i];
            if (query->epoch == e && (query->state == Q_OPEN ||
                                      (query->state == Q_CLOSED &&
                                       ups_ecb__since(ecb->now, query->last) < q))) {
                busy = 1;
            }
        }
        if (!busy) {
            join->next_epoch = (uint8_t)((e + 1u) % 16u);
            *epoch = e;
            *slot = (unsigned)best;
            return 1;
        }
    }
    return 0;
}

/** Send waiting queries while epochs are free; then another census if a Knock came. */
static void pump(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    unsigned epoch = 0u;
    unsigned slot = 0u;
again:
    while (join->g_count > 0u && take_epoch(ecb, &epoch, &slot)) {
        ups_ecb_group_t *group = &join->groups[join->g_head];
        ups_ecb_query_t *query = &join->queries[slot];
        for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) { /* the epoch's old query is gone */
            if (join->queries[i].state == Q_CLOSED && join->queries[i].epoch == epoch) {
                join->queries[i].state = Q_FREE;
            }
        }
        ups_ecb__copy((uint8_t *)query, NULL, (unsigned)sizeof(*query));
        ups_ecb__copy(query->prefix, group->prefix, 8u);
        query->plen = group->plen;
        query->tries = group->tries;
        if (group->set != 0u) { /* the lowest child of the group */
            unsigned n = 0;
            while (!(group->set & (1u << n))) {
                n++;
            }
            group->set = (uint16_t)(group->set & ~(1u << n));
            set_nibble(query->prefix, query->plen, n);
            query->plen++;
            query->tries = 0u;
        }
        if (group->set == 0u) {
            join->g_head = (uint8_t)ring(join, 1u);
            join->g_count--;
            if (join->g_counted > 0u) {
                join->g_counted--;
            }
        }
        query->state = Q_OPEN;
        query->epoch = (uint8_t)epoch;
        query->sent = ecb->now;
        query->last = ecb->now;
        query->set_stage = NIBBLES;
        query->seq = join->seq++;
        join->sent++;
        ups_ecb__count(&ecb->counters.census_queries);
        if (query->plen == 0u) {
            ups_ecb__send8(ecb, (OP_STATUS << 12) | epoch, NULL); /* Census: status 0 */
        } else {
            unsigned last = nibble_at(query->prefix, query->plen - 1u);
            unsigned field = (OP_QUERY << 12) | (epoch << 8) | ((query->plen - 1u) << 4) | last;
            ups_ecb__send8(ecb, field, query->prefix);
        }
    }
    for (unsigned i = join->g_counted; i < join->g_count; i++) { /* branches that wait */
        unsigned set = join->groups[ring(join, i)].set;
        for (unsigned k = set != 0u ? popcount16(set) : 1u; k > 0u; k--) {
            ups_ecb__count(&ecb->counters.queries_waiting);
        }
    }
    join->g_counted = join->g_count;
    if (!ups_ecb__join_busy(ecb) && join->again && ecb->elect.role != UPS_ECB_STANDBY) {
        join->again = 0u; /* knock() again, as a loop (no recursion: a bounded stack) */
        ups_ecb__count(&ecb->counters.census_knocks);
        start_census(ecb);
        goto again;
    }
}

/** The open query of @p epoch, else the closed one it last carried, reopened when it had no
 *  answer at all and @p stage is at or past its prefix; NULL when neither. */
static ups_ecb_query_t *query_of(ups_ecb_t *ecb, unsigned epoch, unsigned stage, int *closed)
{
    ups_ecb_join_t *join = &ecb->join;
    ups_ecb_query_t *last = NULL;
    *closed = 0;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        ups_ecb_query_t *query = &join->queries[i];
        if (query->epoch == epoch && query->state == Q_OPEN) {
            return query;
        }
        if (query->epoch == epoch && query->state == Q_CLOSED) {
            last = query;
        }
    }
    if (last == NULL) {
        return NULL;
    }
    if (last->present == 0u && stage >= last->plen) { /* its answers come late, not never */
        ups_ecb__count(&ecb->counters.census_reopened);
        late(ecb, ups_ecb__since(ecb->now, last->sent));
        last->state = Q_OPEN;
        last->sent = ecb->now; /* a window of its own from now on */
        last->last = ecb->now;
        last->late = 0u;
        last->seq = join->seq++;
        return last;
    }
    *closed = 1;
    return last;
}

/** A Stage for the query its epoch last carried, which has closed: once the query's first
 *  stages came late, it was a joiner's late answer, and the census waits longer. */
static void late_stage(ups_ecb_t *ecb, ups_ecb_query_t *query, unsigned stage)
{
    uint32_t age = ups_ecb__since(ecb->now, query->sent);
    if (age > LONGEST + SLACK_MAX || stage < query->plen) {
        return;
    }
    query->late = (uint16_t)(query->late | (1u << stage));
    unsigned end = query->plen + LATE_QUORUM < NIBBLES ? query->plen + LATE_QUORUM : NIBBLES;
    unsigned wanted = ((1u << end) - 1u) & ~((1u << query->plen) - 1u);
    if ((query->late & wanted) == wanted) {
        query->late = 0u;
        late(ecb, age);
    }
}

static void on_stage(ups_ecb_t *ecb, unsigned epoch, unsigned stage, unsigned nibble)
{
    int closed = 0;
    ups_ecb_query_t *query = query_of(ecb, epoch, stage, &closed);
    if (query == NULL || closed || stage < query->plen) {
        ups_ecb__count(&ecb->counters.census_late_stages);
        if (query != NULL && closed) {
            late_stage(ecb, query, stage);
        }
        return;
    }
    ups_ecb__count(&ecb->counters.census_stages);
    ups_ecb_join_t *join = &ecb->join;
    if (query->present == 0u) { /* its first answer: the round trip */
        uint32_t d = ups_ecb__since(ecb->now, query->sent);
        int32_t rtt = (int32_t)join->rtt;
        rtt += ((int32_t)(d > 60000u ? 60000u : d) - rtt) / 4;
        join->rtt = (uint16_t)(rtt < 0 ? 0 : rtt);
    }
    uint16_t bit = (uint16_t)(1u << stage);
    if (!(query->present & bit)) {
        query->present = (uint16_t)(query->present | bit);
        set_nibble(query->prefix, stage, nibble);
    } else if (nibble_at(query->prefix, stage) != nibble || (query->many & bit)) {
        if (!(query->many & bit)) {
            query->many = (uint16_t)(query->many | bit);
            if (stage < query->set_stage) { /* the first stage with several, from now on */
                query->set_stage = (uint8_t)stage;
                query->set = (uint16_t)(1u << nibble_at(query->prefix, stage));
            }
        }
        if (stage == query->set_stage) {
            query->set = (uint16_t)(query->set | (1u << nibble));
        }
    }
    query->last = ecb->now;
}

static void retry(ups_ecb_t *ecb, const ups_ecb_query_t *query, const uint8_t *certain,
                  unsigned len)
{
    unsigned tries = (len == query->plen ? query->tries : 0u) + 1u;
    if (tries <= RETRIES && ecb->join.retries < RETRY_BUDGET) {
        ecb->join.retries++;
        ups_ecb__count(&ecb->counters.census_retries);
        follow(ecb, certain, len, 0u, tries);
    }
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
    while (len < NIBBLES && (query->present & (1u << len)) && !(query->many & (1u << len))) {
        len++;
    }
    uint16_t wanted = (uint16_t)(0xFFFFu & ~((1u << query->plen) - 1u));
    if ((query->present & wanted) != wanted) { /* incomplete: ask again what is certain */
        ups_ecb__count(&ecb->counters.census_incomplete);
        retry(ecb, query, prefix, len);
        return;
    }
    if (len == NIBBLES) {
        found(ecb, prefix);
    } else if (len == NIBBLES - 1u) { /* several at the last stage: whole ids at once */
        for (unsigned n = 0; n < 16u; n++) {
            if (query->set & (1u << n)) {
                set_nibble(prefix, len, n);
                found(ecb, prefix);
            }
        }
    } else { /* several joiners: a query for each branch */
        follow(ecb, prefix, len, query->set, 0u);
    }
}

static void census_tick(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    uint32_t s = slack(ecb);
    if (s == 0u) {
        join->slack0 = 0u;
    }
    uint32_t first = 4u * join->rtt;
    first = first < FIRST_MIN ? FIRST_MIN : (first > FIRST_MAX ? FIRST_MAX : first);
    first = first > s ? first : s;
    uint32_t quiet = s / 4u > QUIET ? s / 4u : QUIET;
    int closed_any = 0;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) { /* closed ones may stay for weeks */
        if (join->queries[i].state == Q_CLOSED) {
            (void)ups_ecb__age(ecb->now, &join->queries[i].sent);
            (void)ups_ecb__age(ecb->now, &join->queries[i].last);
        }
    }
    for (;;) { /* the due queries, in the order they were opened */
        ups_ecb_query_t *next = NULL;
        for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
            ups_ecb_query_t *query = &join->queries[i];
            if (query->state != Q_OPEN) {
                continue;
            }
            uint32_t age = ups_ecb__since(ecb->now, query->sent);
            int due = (age >= first && ups_ecb__since(ecb->now, query->last) >= quiet) ||
                      age >= LONGEST + s;
            if (due && (next == NULL || (int16_t)(uint16_t)(query->seq - next->seq) < 0)) {
                next = query;
            }
        }
        if (next == NULL) {
            break;
        }
        next->state = Q_CLOSED;
        next->last = ecb->now;
        next->late = 0u;
        conclude(ecb, next);
        closed_any = 1;
    }
    if (closed_any || join->g_count > 0u || join->again) {
        pump(ecb);
    }
}

/* ==== the join's frames =================================================================== */

void ups_ecb__join_rx(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    (void)len;
    unsigned txnode = (id >> UPS_ECB__TXNODE_SHIFT) & 0x7Fu;
    unsigned field = id & UPS_ECB__ETAG_MASK;
    if (txnode != UPS_ECB__MGMT) { /* CLAIM */
        on_claim(ecb, txnode, data);
        return;
    }
    if (field >> 12 == 0u) { /* Stage */
        if (!ecb->recovering) {
            on_stage(ecb, (field >> 8) & 0xFu, (field >> 4) & 0xFu, field & 0xFu);
        }
        return;
    }
    if (field == ((OP_STATUS << 12) | (ST_KNOCK << 8))) {
        if (ecb->recovering) {
            ecb->knocked = 1u; /* answered when the recovery window ends */
        } else {
            knock(ecb);
        }
    }
}

void ups_ecb__join_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data)
{
    unsigned field = id & UPS_ECB__ETAG_MASK;
    unsigned op = field >> 12;
    unsigned status = (field >> 8) & 0xFu;
    int slot = entry_of(ecb, data);
    const ups_ecb_node_t *node = slot != UPS_ECB__NO_SLOT ? &ecb->join.nodes[slot] : NULL;
    int held = node != NULL && (node->flags & UPS_ECB__HELD);
    if (op == OP_ASSIGN && !(field & OFFER_BIT)) { /* Assign of an id the table gives another */
        if (held && node->txnode != (field & 0x7Fu)) {
            ups_ecb__count(&ecb->counters.conflicts);
            send_assign(ecb, node->txnode, node->node_id, 0);
        }
        return;
    }
    if (op == OP_STATUS && (status == ST_TXNODES_FULL || status == ST_FAILED) && node != NULL) {
        if (held) {
            ups_ecb__count(&ecb->counters.conflicts);
            send_assign(ecb, node->txnode, node->node_id, 0);
        } else if (node->flags & UPS_ECB__OFFERED) {
            ups_ecb__count(&ecb->counters.conflicts);
            send_assign(ecb, node->txnode, node->node_id, 1);
        }
    }
}

void ups_ecb__join_tick(ups_ecb_t *ecb)
{
    lapse_offers(ecb);
    census_tick(ecb);
}

void ups_ecb__join_stop(ups_ecb_t *ecb)
{
    ups_ecb_join_t *join = &ecb->join;
    for (unsigned i = 0; i < UPS_ECB_QUERIES; i++) {
        join->queries[i].state = Q_FREE;
    }
    join->g_count = 0u;
    join->g_counted = 0u;
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
    if (size % ENTRY_BYTES != 0u || size > (size_t)UPS_ECB_NODES * ENTRY_BYTES) {
        return UPS_ERR_ARGUMENT;
    }
    for (size_t n = 0; n < size; n += ENTRY_BYTES) {
        unsigned slot = in[n];
        unsigned txnode = in[n + 1u];
        if (slot >= UPS_ECB_NODES || txnode >= TXNODES ||
            ecb->join.nodes[slot].txnode != 0xFFu || ups_ecb__holder(ecb, txnode) >= 0 ||
            entry_of(ecb, &in[n + 2u]) >= 0) {
            return UPS_ERR_ARGUMENT; /* out of range, or twice: not a blob this library wrote */
        }
        ups_ecb_node_t *node = &ecb->join.nodes[slot];
        ups_ecb__copy(node->node_id, &in[n + 2u], 8u);
        node->txnode = (uint8_t)txnode;
        node->flags = UPS_ECB__HELD;
        node->age = 0u;
    }
    return UPS_OK;
}
