/*
 * libups-ecb: the CAN-ECB of a UPS bus (docs/protocol.md, its CAN part), in C99, for a
 * microcontroller, so that a bus of microcontrollers runs UPS with no computer on it.
 *
 * It does on the wire what the Python CAN-ECB (broker/can_ecb.py) does: it gives TxNodes to
 * joining nodes (Knock, Census, Query, Offer, CLAIM, Assign, moves, TxNodesFull), binds channel
 * UIDs to etags (size classes, the contradiction rule, EtagsFull, Limit, the quota, UNSUB),
 * says Hello and adopts what the nodes report in the recovery window, corrects forged frames,
 * takes part in the election with any other CAN-ECB of the bus, answers the gateways' Roster,
 * and admits declared real-time streams by the response-time analysis of ups/rt (ups_ecb_rt.c).
 *
 * Its shape is libups's (and libcanard's): no heap, no OS, no I/O, no floating point, no C
 * library call. The application
 *   - calls ups_ecb_init(), then ups_ecb_restore() with the blob it saved (if any), then
 *     ups_ecb_start();
 *   - feeds every received frame to ups_ecb_rx();
 *   - calls ups_ecb_tick() with the time, at least every few milliseconds;
 *   - reads ups_ecb_notes() after every call: on UPS_ECB_NOTE_STATE it writes the blob
 *     (ups_ecb_save()) to its flash *before* it sends the frames queued since, so that nothing
 *     is announced on the bus that a reset would forget;
 *   - takes the frames to send with ups_ecb_tx_peek()/ups_ecb_tx_pop(), lowest identifier first.
 *
 * Time is a uint32_t count of milliseconds from any origin, wrapping freely.
 *
 * Every table is sized at compile time by the macros below; each bound is counted when hit
 * (ups_ecb_counters_t). ups_ecb_t is the whole state: place one (static storage is fine) and
 * pass it to every call, from one context only. It may share an image with a libups node
 * (ups.h): the two are independent, and the application passes every frame to both.
 */
#ifndef UPS_ECB_H
#define UPS_ECB_H

#include "ups.h" /* ups_frame_t, UPS_FRAME_..., UPS_OK, UPS_ERR_... */

#ifdef __cplusplus
extern "C" {
#endif

/* ---- compile-time configuration ------------------------------------------------------------ */

/** Node ids the CAN-ECB assigns a TxNode to (nodes of the bus, present or remembered), 1..127. */
#ifndef UPS_ECB_NODES
#define UPS_ECB_NODES 16
#endif

/** Channels bound at once (UID -> etag), 1..16368. */
#ifndef UPS_ECB_CHANNELS
#define UPS_ECB_CHANNELS 64
#endif

/** Declared real-time streams admitted at once, 0..126 (0 leaves admission out: every
 *  DECLARE is answered with a Refuse). */
#ifndef UPS_ECB_STREAMS
#define UPS_ECB_STREAMS 4
#endif

/** Census queries open at once (epochs), 1..16. */
#ifndef UPS_ECB_QUERIES
#define UPS_ECB_QUERIES 4
#endif

/** Frames waiting to be sent, 4..255. */
#ifndef UPS_ECB_TX_DEPTH
#define UPS_ECB_TX_DEPTH 16
#endif

/** Binding requests held during the recovery window (answered when it ends), 1..4096. */
#ifndef UPS_ECB_HELD
#define UPS_ECB_HELD 8
#endif

/** Requests a standing-by CAN-ECB watches for an answer at once, 1..1024. */
#ifndef UPS_ECB_WATCHED
#define UPS_ECB_WATCHED 4
#endif

/** Rosters waiting to be answered at once (one per asking node: only gateways ask, and a bus
 *  has few), 1..127. Past it, the Roster of a node that has none waiting is not kept (counted:
 *  rosters_full); the node asks again. */
#ifndef UPS_ECB_ROSTERS
#define UPS_ECB_ROSTERS 4
#endif

/** CAN-ECB frames remembered after they were sent (12 bytes each: identifier and data, so
 *  that no other frame passes for one), so that one heard again within a second (an echo: a
 *  controller or a bus that hands a sender its own frames, or an application that feeds what it
 *  sent back in) is known for its own, 0..1024. Frames still queued are always known. */
#ifndef UPS_ECB_ECHOES
#define UPS_ECB_ECHOES 16
#endif

/** The type of the counters (saturating). */
#ifndef UPS_ECB_COUNTER_T
#define UPS_ECB_COUNTER_T uint32_t
#endif

#if UPS_ECB_NODES < 1 || UPS_ECB_NODES > 127
#error "UPS_ECB_NODES must be 1..127"
#endif
#if UPS_ECB_CHANNELS < 1 || UPS_ECB_CHANNELS > 16368
#error "UPS_ECB_CHANNELS must be 1..16368"
#endif
#if UPS_ECB_STREAMS < 0 || UPS_ECB_STREAMS > 126
#error "UPS_ECB_STREAMS must be 0..126"
#endif
#if UPS_ECB_ECHOES < 0 || UPS_ECB_ECHOES > 1024
#error "UPS_ECB_ECHOES must be 0..1024"
#endif
#if UPS_ECB_ROSTERS < 1 || UPS_ECB_ROSTERS > 127
#error "UPS_ECB_ROSTERS must be 1..127"
#endif
#if UPS_ECB_QUERIES < 1 || UPS_ECB_QUERIES > 16 || UPS_ECB_TX_DEPTH < 4 || UPS_ECB_TX_DEPTH > 255
#error "UPS_ECB_QUERIES must be 1..16 and UPS_ECB_TX_DEPTH 4..255"
#endif

/* ---- run-time configuration ---------------------------------------------------------------- */

/** What a CAN-ECB may be told at ups_ecb_init() (ups_ecb_default_config() fills the defaults,
 *  the Python CAN-ECB's). */
typedef struct {
    uint32_t bitrate;      /**< bit/s of the bus, for the admission analysis (500000) */
    uint8_t fd;            /**< 1: declared streams are analysed as CAN FD frames (0) */
    uint16_t recovery_ms;  /**< the recovery window after Hello, 100..10000 (2000) */
    uint32_t lease_s;      /**< a TxNode or etag unused this long may be reclaimed (86400),
                                1..1000000 (ages are counted in fractions of it, so that
                                the clock's wraps never make an old entry young) */
    uint16_t max_channels; /**< channels one TxNode may use (UPS_ECB_CHANNELS) */
    uint16_t quota[5];     /**< bindings one node id may create, per size class
                                (1024, 64, 64, 64, 64) */
} ups_ecb_config_t;

/* ---- roles, notes, counters ---------------------------------------------------------------- */

#define UPS_ECB_STOPPED 0   /**< ups_ecb_role(): not started */
#define UPS_ECB_CANDIDATE 1 /**< said Hello; serves unless another CAN-ECB serves already */
#define UPS_ECB_SERVING 2   /**< answers the bus */
#define UPS_ECB_STANDBY 3   /**< another CAN-ECB serves; this one watches and answers nothing */

#define UPS_ECB_NOTE_STATE 0x01u    /**< the durable state changed: save the blob
                                         (ups_ecb_save) before sending any frame queued
                                         since (the Assign or Bind that announces it): so a
                                         reset never forgets what the bus was told */
#define UPS_ECB_NOTE_ROLE 0x02u     /**< ups_ecb_role() changed */
#define UPS_ECB_NOTE_CHANNELS 0x04u /**< who uses which channel changed (a gateway's) */

/** What the CAN-ECB ignored, turned away or gave up, each counted (saturating). The names
 *  are the Python CAN-ECB's (its stats), and the bounds of this library's tables. */
typedef struct {
    UPS_ECB_COUNTER_T joined;      /**< Assigns after a census or a claim */
    UPS_ECB_COUNTER_T bound;       /**< new bindings */
    UPS_ECB_COUNTER_T requests;    /**< requests heard (SUB_BIND, PUB_BIND, UNSUB, ...) */
    UPS_ECB_COUNTER_T malformed;   /**< management frames matching no row of the tables */
    UPS_ECB_COUNTER_T foreign;     /**< not UPS: 11-bit, remote, error, FD management frames */
    UPS_ECB_COUNTER_T refused;     /**< declarations refused */
    UPS_ECB_COUNTER_T admitted;    /**< declarations admitted */
    UPS_ECB_COUNTER_T adopted;     /**< claims and reports adopted in a recovery window */
    UPS_ECB_COUNTER_T conflicts;   /**< reports or Binds that contradict the tables */
    UPS_ECB_COUNTER_T foreign_ecb_frames; /**< CAN-ECB frames this one did not send */
    UPS_ECB_COUNTER_T unassigned;  /**< requests from a TxNode no node holds */
    UPS_ECB_COUNTER_T deferred;    /**< requests held in a recovery window */
    UPS_ECB_COUNTER_T limited;     /**< Limit sent, and DECLAREs past their rate */
    UPS_ECB_COUNTER_T reclaimed;   /**< TxNodes and etags reclaimed past the lease */
    UPS_ECB_COUNTER_T offers_withdrawn; /**< Offers that lapsed unclaimed */
    UPS_ECB_COUNTER_T moved;       /**< channels moved to a larger size class, TxNode moves */
    UPS_ECB_COUNTER_T late_claims; /**< claims of a lapsed Offer */
    UPS_ECB_COUNTER_T quota_hit;   /**< requests past a node id's quota */
    UPS_ECB_COUNTER_T unanswered_takeovers; /**< took over: a request went unanswered */
    UPS_ECB_COUNTER_T census_knocks;
    UPS_ECB_COUNTER_T census_censuses;
    UPS_ECB_COUNTER_T census_stages;
    UPS_ECB_COUNTER_T census_late_stages;
    UPS_ECB_COUNTER_T census_queries;
    UPS_ECB_COUNTER_T census_reopened;
    UPS_ECB_COUNTER_T census_incomplete;
    UPS_ECB_COUNTER_T census_cut;
    UPS_ECB_COUNTER_T census_retries;
    /* this library's bounds */
    UPS_ECB_COUNTER_T tx_dropped;    /**< frames that did not fit the TX queue (and admissions
                                          whose Grants did not: the DECLARE asked again is) */
    UPS_ECB_COUNTER_T nodes_full;    /**< TxNodesFull sent: the node table is full */
    UPS_ECB_COUNTER_T channels_full; /**< EtagsFull sent because UPS_ECB_CHANNELS is reached */
    UPS_ECB_COUNTER_T streams_full;  /**< declarations refused: UPS_ECB_STREAMS reached */
    UPS_ECB_COUNTER_T held_dropped;  /**< requests not held: UPS_ECB_HELD reached */
    UPS_ECB_COUNTER_T watched_full;  /**< requests not watched: UPS_ECB_WATCHED reached */
    UPS_ECB_COUNTER_T queries_waiting; /**< census branches that waited for a free epoch */
    UPS_ECB_COUNTER_T blob_refused;  /**< ups_ecb_restore() of a corrupt or truncated blob */
    UPS_ECB_COUNTER_T rosters_full;  /**< Rosters not kept: UPS_ECB_ROSTERS of other nodes
                                          wait (the node asks again) */
    /* the Roster's answers (the Python CAN-ECB's names) */
    UPS_ECB_COUNTER_T rosters;         /**< Rosters asked (answered, replaced or not kept) */
    UPS_ECB_COUNTER_T roster_frames;   /**< Uses and RosterEnd frames sent in answer */
    UPS_ECB_COUNTER_T roster_replaced; /**< Rosters replaced by a newer one of the same node
                                            while waiting */
} ups_ecb_counters_t;

/* ---- the CAN-ECB --------------------------------------------------------------------------- */

/* the parts' private state, one header each (their sources own them) */
#include "ups_ecb_join.h"  /* ups_ecb_join_t */
#include "ups_ecb_bind.h"  /* ups_ecb_bind_t */
#include "ups_ecb_elect.h" /* ups_ecb_elect_t */

/* the admission analyses at most UPS_ECB_STREAMS streams at once (ups_ecb_rt.h's arrays, on the
 * stack of ups_ecb_rx, have UPS_ECB_RT_MAX entries: a small bus sets it to UPS_ECB_STREAMS) */
/* an admission queues a Grant for every stream whose priority moves, all or none */
#if UPS_ECB_TX_DEPTH < UPS_ECB_STREAMS
#error "UPS_ECB_TX_DEPTH must be at least UPS_ECB_STREAMS"
#endif
#if UPS_ECB_STREAMS > UPS_ECB_RT_MAX
#error "UPS_ECB_RT_MAX must be at least UPS_ECB_STREAMS"
#endif

/** A frame waiting to be sent: the CAN-ECB sends classic frames only, so its queue keeps 8
 *  data bytes a frame whatever UPS_MTU an image that also holds a CAN FD node has (its length:
 *  ups_ecb_t.tx_len, 13 bytes a frame in all). */
typedef struct {
    uint32_t id;
    uint8_t data[8];
} ups_ecb_frame_t;

/** A frame the CAN-ECB sent lately (UPS_ECB_ECHOES of them), 12 bytes: its frames all have
 *  TxNode 0x7F, priority 0 or 1, and 0 or 8 data bytes, so 16 bits name the identifier and the
 *  length. */
typedef struct {
    uint16_t key;    /* the etag field, bit 14 for priority 0, bit 15 for 8 data bytes; 0 (a
                        priority-1 frame without data: none is sent) an unused entry */
    uint16_t t;      /* low 16 bits of the time it was sent */
    uint8_t data[8]; /* zero without data */
} ups_ecb_echo_t;

/** The whole state of one CAN-ECB. Private: set up with ups_ecb_init(), then use the
 *  functions. */
typedef struct ups_ecb {
    /* the small fields first, then the parts' states: most offsets fit Thumb's short forms */
    uint32_t now;         /* the latest time given */
    uint8_t notes;
    uint8_t recovering;   /* in a recovery window: listen and adopt */
    uint8_t knocked;      /* a Knock came in the recovery window */
    uint8_t started_up;   /* the first recovery is over */
    uint8_t tx_count;
    uint16_t echo_next;   /* the next entry of echo[] to write */
    uint32_t t_recovery;  /* when the recovery window began */
    uint32_t t_unknown_hello; /* the last Hello for an unknown TxNode (HELLO_GAP before the
                                 start: the first one goes at once) */
    ups_ecb_config_t cfg;
    uint8_t instance[8];  /* big-endian */
    uint8_t strays[16];   /* TxNodes heard asking while unknown since the last Hello (bits) */
    ups_ecb_counters_t counters;
    ups_ecb_join_t join;   /* ups_ecb_join.c: TxNodes, the census, Offers */
    ups_ecb_elect_t elect; /* ups_ecb_elect.c: the election */
    ups_ecb_echo_t echo[UPS_ECB_ECHOES > 0 ? UPS_ECB_ECHOES : 1]; /* CAN-ECB frames sent
                                    lately: heard again, they are this one's own */
    ups_ecb_frame_t tx[UPS_ECB_TX_DEPTH]; /* waiting to be sent, in the order queued */
    uint8_t tx_len[UPS_ECB_TX_DEPTH];     /* their lengths */
    ups_frame_t tx_head;  /* the one to send first, as ups_ecb_tx_peek() hands it out */
    ups_ecb_bind_t bind;   /* ups_ecb_bind.c: etags, who uses them, quotas, held requests,
                              rosters, declared streams */
} ups_ecb_t;

/** The defaults (the Python CAN-ECB's). */
void ups_ecb_default_config(ups_ecb_config_t *cfg);

/** Set up @p ecb with @p cfg (NULL: the defaults) and a random @p instance (it names this run:
 *  draw it from a hardware random source, a serial number and a reset counter, ...). Empty
 *  tables. UPS_ERR_ARGUMENT for a configuration out of range. */
int ups_ecb_init(ups_ecb_t *ecb, const ups_ecb_config_t *cfg, uint64_t instance);

/** Take back the durable state saved by ups_ecb_save() in an earlier run, after ups_ecb_init()
 *  and before ups_ecb_start(). UPS_ERR_ARGUMENT (counted in blob_refused, the tables stay
 *  empty) for a blob that is corrupt, truncated, of another format or larger than the tables:
 *  the CAN-ECB then relearns the bus from the nodes' answers to its Hello. */
int ups_ecb_restore(ups_ecb_t *ecb, const uint8_t *blob, size_t size);

/** Start: say Hello and listen for the recovery window. */
void ups_ecb_start(ups_ecb_t *ecb, uint32_t now_ms);

/** Feed one received frame (any frame of the bus, the CAN-ECB's own echoes included). */
void ups_ecb_rx(ups_ecb_t *ecb, uint32_t now_ms, const ups_frame_t *frame);

/** Pass the time: timers of the census, Offers, the recovery window, the election. */
void ups_ecb_tick(ups_ecb_t *ecb, uint32_t now_ms);

/** The next frame to send (lowest identifier first), or NULL. */
const ups_frame_t *ups_ecb_tx_peek(const ups_ecb_t *ecb);

/** Remove the frame ups_ecb_tx_peek() returned (it was sent). */
void ups_ecb_tx_pop(ups_ecb_t *ecb);

/** What changed since the last call (UPS_ECB_NOTE_...), cleared by reading. */
unsigned ups_ecb_notes(ups_ecb_t *ecb);

/** The largest blob ups_ecb_save() writes with these tables (its format: ups_ecb.c). */
#define UPS_ECB_BLOB_MAX \
    (20u + 12u * UPS_ECB_NODES + 12u * UPS_ECB_CHANNELS + 12u * UPS_ECB_STREAMS)

/** Write the durable state (TxNodes by node id, etags by UID and creator, admitted streams) to
 *  @p out as a self-checking blob (a header, the sections, a CRC-32); returns its size, or 0
 *  when @p cap is below UPS_ECB_BLOB_MAX.
 *
 *  Write rate: the blob changes (UPS_ECB_NOTE_STATE) only when the durable state does: a node
 *  joins for the first time or is moved (one change per Assign of a TxNode it did not hold),
 *  a TxNode is adopted in a recovery window or reclaimed past the lease, a channel is bound
 *  for the first time, moved to a larger size class or reclaimed, or a stream is admitted or
 *  given up. A bus whose nodes and channels are known writes nothing, whatever it exchanges
 *  and however often its nodes restart (a rejoin under the same id is no change); a bus of
 *  N nodes and C channels that starts from nothing writes at most N + C times, and an
 *  application that saves once per call of ups_ecb_rx()/ups_ecb_tick() that raised the note
 *  (not once per change) writes fewer. With 10 000 erase cycles per flash sector and two
 *  sectors used in turn, that is 20 000 such changes. */
size_t ups_ecb_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap);

/** UPS_ECB_STOPPED, UPS_ECB_CANDIDATE, UPS_ECB_SERVING or UPS_ECB_STANDBY. */
int ups_ecb_role(const ups_ecb_t *ecb);

const ups_ecb_counters_t *ups_ecb_counters(const ups_ecb_t *ecb);

/** The tables, for a status display. The i-th node (0 <= i < UPS_ECB_NODES): its TxNode, and
 *  its id in @p node_id; -1 for an unused entry. */
int ups_ecb_node(const ups_ecb_t *ecb, int i, uint64_t *node_id);

/** The i-th channel (0 <= i < UPS_ECB_CHANNELS): its etag, and its UID in @p uid; -1 for an
 *  unused entry. */
int ups_ecb_channel(const ups_ecb_t *ecb, int i, uint64_t *uid);

/** Who uses the i-th channel: the TxNodes that subscribe to it in @p subscribers and those
 *  that publish on it in @p publishers (TxNode t: bit t % 8 of byte t / 8), of the node
 *  entries that hold a TxNode. Returns its etag, or -1 (both zero) for an unused entry or an
 *  @p i out of range. One call a channel, for a status display. */
int ups_ecb_channel_users(const ups_ecb_t *ecb, int i, uint8_t subscribers[16],
                          uint8_t publishers[16]);

#ifdef __cplusplus
}
#endif

#endif /* UPS_ECB_H */
