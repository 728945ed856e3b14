/*
 * libups-ecb, private: the state of ups_ecb_bind.c (etags by UID, who uses them, quotas, held
 * requests, rosters, declared streams). Included by ups_ecb.h; not part of the API.
 *
 * Who uses a channel and who created its binding are kept per node entry (the index into
 * ups_ecb_join_t.nodes), not per TxNode: a bitmap of node entries for the subscribers and one
 * for the publishers. A channel's age counts sixteenths of the lease since its last event
 * (ups_ecb__bind_tick ages every channel), so leases need no timestamps and survive the clock's
 * wraps. With the small bus's tables (16 nodes, 64 channels, 4 streams, 8 held requests, 4
 * waiting Rosters) this state is 1244 bytes (Cortex-M0+ and host alike), of which the channels
 * take 1024.
 */
#ifndef UPS_ECB_BIND_H
#define UPS_ECB_BIND_H

#include <stdint.h>

#include "ups_ecb_rt.h" /* ups_ecb_stream_t */

/** Bytes of a bitmap of node entries. */
#define UPS_ECB_NODE_BYTES ((UPS_ECB_NODES + 7) / 8)

typedef struct {
    uint8_t uid[8];   /* big-endian */
    uint16_t etag;    /* 0: unused entry */
    uint8_t creator;  /* 1 + the node entry (ups_ecb_join_t.nodes) that created it; 0: nobody */
    uint8_t age;      /* sixteenths of the lease since its last event (saturating) */
    uint8_t use[2][UPS_ECB_NODE_BYTES]; /* node entries that subscribe to it [0], publish [1] */
} ups_ecb_channel_t;

/** A Roster waiting to be answered (UPS_ECB_ROSTERS of them at once). */
typedef struct {
    uint8_t slot;      /* the asker's node entry */
    uint8_t cursor[8]; /* the UID it asked from, big-endian */
} ups_ecb_roster_t;

/** A binding request held in a recovery window. */
typedef struct {
    uint8_t uid[8];
    uint8_t txnode;
    uint8_t kind; /* 0: none; the request's etag field (1 PUB_BIND, 2 SUB_BIND, 9-12 PUB_BIND(c)) */
} ups_ecb_held_t;

typedef struct {
    /* the scalars first (short offsets on Thumb), then the tables */
    uint32_t t_roster;       /* the roster's tokens were counted up to then */
    uint32_t t_decl;         /* the DECLARE tokens were counted up to then */
    uint32_t t_aged;         /* the channels were aged up to then */
    uint16_t r_count;        /* Uses frames of this page */
    uint8_t timed;           /* the three times above are set (the first tick) */
    uint8_t stream_count;
    uint8_t refused_valid;   /* the refusal below answers its declaration again */
    uint8_t r_waiting;       /* entries of rosters[] */
    uint8_t r_active;        /* an answer is being sent */
    uint8_t r_asker;         /* its TxNode */
    uint8_t r_role;          /* what it lists next (R_... in ups_ecb_bind.c) */
    uint8_t r_from;          /* the next TxNode to list in that role is this or above */
    uint8_t r_tokens;        /* roster frames that may be sent back to back now (<= 48) */
    uint8_t r_uid[8];
    ups_ecb_channel_t channels[UPS_ECB_CHANNELS];
    ups_ecb_held_t held[UPS_ECB_HELD];
    ups_ecb_stream_t streams[UPS_ECB_STREAMS > 0 ? UPS_ECB_STREAMS : 1]; /* admitted, sorted
                                                                  by (etag, TxNode) */
    uint8_t refused_decl[8]; /* the DECLARE data last refused (its TxNode: refuse[2]) */
    uint8_t refuse[8];       /* the Refuse data last sent; refuse[0..1] == 0: none */
    uint8_t spent[UPS_ECB_NODES]; /* DECLARE analyses each node entry asked lately (<= 20) */
    ups_ecb_roster_t rosters[UPS_ECB_ROSTERS]; /* waiting, one per node entry, oldest first */
} ups_ecb_bind_t;

#endif /* UPS_ECB_BIND_H */
