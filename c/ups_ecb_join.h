/*
 * libups-ecb, private: the state of ups_ecb_join.c (TxNodes by node id, the census, Offers).
 * Included by ups_ecb.h after its configuration macros; not part of the API.
 *
 * RAM: 13 bytes per node entry (its Offer's time apart: no padding), 28 per census query
 * (UPS_ECB_QUERIES), 12 per waiting branch group (UPS_ECB__GROUPS) and 24 more: 440 bytes
 * for the small bus (16 nodes, 4 queries). A group holds every branch of one stage, so a
 * census's waiting branches take few groups: one per branching of the ids found and not yet
 * queried.
 */
#ifndef UPS_ECB_JOIN_H
#define UPS_ECB_JOIN_H

#include <stdint.h>

/* a node entry's flags */
#define UPS_ECB__HELD 0x01u    /* the node holds txnode (durable: in the blob) */
#define UPS_ECB__OFFERED 0x02u /* txnode is offered to it, since t_offer */
#define UPS_ECB__LAPSED 0x04u  /* an Offer of txnode lapsed unclaimed (not held): a late claim
                                  still gets it; the entry is given up first when none is free */
#define UPS_ECB__PROBATION 0x08u /* held, adopted from a stray's CLAIM (or a stray's id moved
                                    there) and silent since (soft: not in the blob): reclaimed
                                    first when none is free */

/** One node id the CAN-ECB knows: it holds a TxNode, is offered one, or let an Offer lapse.
 *  txnode is 0xFF in an unused entry (whose flags are 0). age counts 64ths of the lease since
 *  its TxNode's last frame (held), or since its Offer lapsed (lapsed), saturating:
 *  ups_ecb__join_tick ages every entry, so leases need no timestamps and no clock wrap makes an
 *  old entry young. */
typedef struct {
    uint8_t node_id[8]; /* big-endian */
    uint8_t txnode;     /* 0xFF: unused entry */
    uint8_t flags;      /* UPS_ECB__HELD, ... */
    uint8_t age;        /* 64ths of the lease (UPS_ECB__LEASE_AGE: the lease has passed) */
} ups_ecb_node_t;

/** An age (ups_ecb_node_t.age) at which the lease has passed. */
#define UPS_ECB__LEASE_AGE 64u

/** A census query: open (collecting Stage frames), or closed and remembered for the late
 *  answers of its epoch (until its slot is needed again). */
typedef struct {
    uint32_t sent;      /* when it was sent (or reopened) */
    uint32_t last;      /* open: the latest Stage for it; closed: when it closed */
    uint8_t prefix[8];  /* its prefix, left-aligned (the Query's data, the rest zero when it
                           is sent), then at each stage s past it the nibble heard (high half
                           of prefix[s / 2] for even s) */
    uint16_t present;   /* stages at which a nibble was heard */
    uint16_t many;      /* open: stages at which several were (the lowest is the first with
                           several); closed: the stages of its late answers */
    uint16_t set;       /* the nibbles of the first stage with several */
    uint16_t seq;       /* open order (the order in which queries close and are read) */
    uint8_t tag;        /* its state (high nibble: 0 free, 1 open, 2 closed) and epoch (low) */
    uint8_t plen;       /* prefix length, 0 (Census) .. 15 */
    uint8_t tries;      /* how often this prefix was asked again */
    uint8_t pad;
} ups_ecb_query_t;

/** Census branches waiting for an epoch: the prefix itself (set 0), or its children, one per
 *  nibble of set (a compact encoding: the branches of one stage share their prefix). */
typedef struct {
    uint8_t prefix[8];
    uint8_t plen;
    uint8_t tries;
    uint16_t set;
} ups_ecb_group_t;

/** Waiting branch groups at once; past it a branch is cut (census_cut): its joiners knock
 *  again and the next census finds them. */
#define UPS_ECB__GROUPS (UPS_ECB_QUERIES + 4)

typedef struct { /* the scalars first: Thumb-1 loads reach only small offsets in one */
    uint32_t late_at;   /* when the slack was last raised */
    uint32_t t_aged;    /* the node entries' ages were counted up to then */
    uint16_t rtt;       /* ms: the round trip from a query to its first Stage, averaged */
    uint16_t slack0;    /* ms: the slack when it was last raised (0: none) */
    uint16_t seq;       /* the next query's open order */
    uint16_t queued;    /* branches sent in this census or waiting in the groups */
    uint16_t uncounted; /* the waiting branches not yet counted in queries_waiting (of the
                           last groups: groups are counted at the end of each pump) */
    uint8_t retries;    /* queries asked again in this census */
    uint8_t again;      /* a Knock came during the census: another one follows */
    uint8_t next_epoch;
    uint8_t g_head;
    uint8_t g_count;
    uint8_t g_counted;  /* of the waiting groups, those counted (from the head) */
    ups_ecb_group_t groups[UPS_ECB__GROUPS]; /* a FIFO ring */
    ups_ecb_node_t nodes[UPS_ECB_NODES];
    uint16_t t_offer[UPS_ECB_NODES];         /* low 16 bits of the time of each entry's Offer */
    ups_ecb_query_t queries[UPS_ECB_QUERIES];
} ups_ecb_join_t;

#endif /* UPS_ECB_JOIN_H */
