/*
 * libups: a UPS (Ulm Publisher/Subscriber) node for CAN, in C99, for microcontrollers.
 *
 * The protocol is docs/protocol.md (its CAN part). This library does what a *node* does there:
 * it joins the bus (Knock, Census and Query answers, CLAIM of an Offer, Assign, moves), binds
 * channels to etags (SUB_BIND, PUB_BIND, PUB_BIND(c), the request retry, the contradiction,
 * doubt and settle rules), answers Hello, sends and receives events, declares real-time
 * streams, and, when compiled in, carries events larger than one frame (transfers) and CAN FD.
 *
 * Its shape is libcanard's: no heap, no OS, no I/O, no floating point. The application
 *   - feeds every received frame to ups_rx(), which may hand back one event;
 *   - takes the frames to send with ups_tx_peek()/ups_tx_pop(), highest priority (lowest
 *     identifier) first, whenever its controller has a free transmit mailbox;
 *   - calls ups_tick() with the time, at least every few milliseconds (every millisecond for
 *     the recommended 1 ms pacing of Hello answers);
 *   - reads what happened with ups_notes() (joined, filters changed, a channel's state changed)
 *     after ups_start() and after every ups_rx() and ups_tick(), and acts on it at once (the
 *     first UPS_NOTE_FILTERS comes from ups_start(): a controller that accepts nothing after
 *     reset gets the node's filters before its first frame goes).
 *
 * Time is a uint32_t count of milliseconds from any origin, wrapping freely: the node keeps its
 * times as the low 16 bits (a refusal's as bits 2-13), so the clock may wrap at any moment.
 * How often ups_tick() must come, and when a node may sleep, is said at ups_tick().
 *
 * Every table is sized at compile time by the macros below (define them before including this
 * header, or with -D, identically for every file). ups_node_t is the whole state: place one
 * (static storage is fine) and pass it to every call. Nothing here is thread-safe or
 * reentrant: make every call on a node from one context, the main loop or the one task that
 * owns the node. Interrupts only copy received frames into a ring and wake that context; a
 * transmit-complete interrupt does not call ups_tx_peek()/ups_tx_pop() (it would race the
 * loop's calls): it wakes the loop, which fills the free mailboxes. See c/README.md, Porting.
 *
 * Every call that can fail returns a negative UPS_ERR_... code; 0 or a positive value is
 * success. Nothing overflows: every table bound is checked, and what it turns away is counted
 * in ups_counters_t.
 *
 * The sources stand in floors: ups.c on top (receiving and its checks, the timers' entry,
 * sending, events), the protocol's seams under it, ups_join.c (the join, moves, the answer to
 * Hello), ups_bind.c (binding, the contradiction rule, declarations) and ups_transfer.c (events
 * larger than one frame), and at the bottom ups_util.c (size classes, byte helpers, counters,
 * the TX queue); each has its internal header (ups_join.h, ..., ups_util.h, which also holds
 * what they all share), included only by the floors above it. Compile all five.
 */
#ifndef UPS_H
#define UPS_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- compile-time configuration ------------------------------------------------------------ */

/** Channels the node uses at once (subscribed, published or both), 1..126. */
#ifndef UPS_CHANNELS
#define UPS_CHANNELS 8
#endif

/** Frames waiting to be sent, 2..255. Answers to Census and Hello and the frames of transfers
 *  are made as room appears, so a few suffice; a full queue turns events away (tx_dropped).
 *  Events never take the last place: it stays for the node's requests and answers. */
#ifndef UPS_TX_DEPTH
#define UPS_TX_DEPTH 8
#endif

/** 1: events larger than one frame (size classes 1-4, transfers with CRC). 0: events of at
 *  most 8 bytes only; channels bound to larger size classes are refused (UPS_ERR_TOO_LARGE). */
#ifndef UPS_WITH_TRANSFERS
#define UPS_WITH_TRANSFERS 0
#endif

/** 1: CAN FD buses (64-byte frames) are supported; ups_init() says whether this bus is one.
 *  0 (classic only): ups_frame_t holds 8 data bytes and the node sends classic frames only.
 *  Event frames may be either kind, so it takes a received CAN FD frame of up to 8 bytes like a
 *  classic one (flag it UPS_FRAME_FD: FD management frames are foreign); a longer one does not
 *  fit ups_frame_t and the port drops it, never cut to 8 bytes (the library could not tell):
 *  such a node receives no transfer sent in 64-byte frames, which it could not take anyway. */
#ifndef UPS_WITH_FD
#define UPS_WITH_FD 0
#endif

/** The largest event the node sends or receives, in bytes (8 without transfers; at most
 *  65535). One transmit buffer and each receive slot hold this much. A subscription to a
 *  channel whose size class carries larger events is refused (UPS_ERR_TOO_LARGE). */
#ifndef UPS_MAX_EVENT
#if UPS_WITH_TRANSFERS
#define UPS_MAX_EVENT 64
#else
#define UPS_MAX_EVENT 8
#endif
#endif

/** Transfers reassembled at once (one per sending TxNode and etag); the oldest is given up
 *  when one more starts (counted in large_lost). Used only with UPS_WITH_TRANSFERS. */
#ifndef UPS_RX_TRANSFERS
#define UPS_RX_TRANSFERS 2
#endif

/** Real-time streams the node declares at once (DECLARE, Grant, Refuse); 0 leaves them out. */
#ifndef UPS_DECLARATIONS
#define UPS_DECLARATIONS 1
#endif

/** Binds of other channels remembered for the doubt rule (an answer naming an etag last heard
 *  bound to another UID is not relied on until it comes again); 0 leaves it out. */
#ifndef UPS_HEARD_BINDS
#define UPS_HEARD_BINDS 0
#endif

/** Milliseconds a join may take before it is given up (UPS_ERR_TIMEOUT), at most 60000;
 *  0: never. */
#ifndef UPS_JOIN_GIVE_UP_MS
#define UPS_JOIN_GIVE_UP_MS 30000u
#endif

/** The type of the counters (saturating): uint16_t saves RAM on the smallest parts. */
#ifndef UPS_COUNTER_T
#define UPS_COUNTER_T uint32_t
#endif

#if UPS_WITH_FD
#define UPS_MTU 64
#else
#define UPS_MTU 8
#endif

#if !UPS_WITH_TRANSFERS && UPS_MAX_EVENT > 8
#error "UPS_MAX_EVENT above 8 needs UPS_WITH_TRANSFERS"
#endif
#if UPS_CHANNELS < 1 || UPS_CHANNELS > 126 || UPS_TX_DEPTH < 2 || UPS_TX_DEPTH > 255
#error "UPS_CHANNELS must be 1..126 and UPS_TX_DEPTH 2..255"
#endif
#if UPS_MAX_EVENT > 65535 || UPS_RX_TRANSFERS < 1 || UPS_DECLARATIONS > UPS_CHANNELS
#error "UPS_MAX_EVENT must be at most 65535, UPS_RX_TRANSFERS at least 1"
#endif
#if UPS_JOIN_GIVE_UP_MS > 60000
#error "UPS_JOIN_GIVE_UP_MS must be at most 60000 (the timers count 16-bit milliseconds)"
#endif

/* ---- results ------------------------------------------------------------------------------- */

#define UPS_OK 0
#define UPS_ERR_ARGUMENT (-1)    /**< an argument out of range (a channel index, a priority, ...) */
#define UPS_ERR_FULL (-2)        /**< a table is full (channels, declarations, the TX queue) */
#define UPS_ERR_UNBOUND (-3)     /**< the channel has no etag this node relies on (yet) */
#define UPS_ERR_TOO_LARGE (-4)   /**< the event exceeds the channel's size class, or the node's;
                                      the channel's events would not fit the node */
#define UPS_ERR_BUSY (-5)        /**< a transfer is still being sent; try again after ups_tx_pop */
#define UPS_ERR_NOT_JOINED (-6)  /**< the node holds no TxNode */
#define UPS_ERR_TIMEOUT (-7)     /**< no answer in time (join: UPS_JOIN_GIVE_UP_MS; binding: 5 s) */
#define UPS_ERR_TXNODES_FULL (-8) /**< TxNodesFull: the CAN-ECB has no TxNode left for this node */
#define UPS_ERR_ETAGS_FULL (-9)  /**< EtagsFull: the CAN-ECB has no etag left for the channel */
#define UPS_ERR_LIMIT (-10)      /**< Limit: this node uses as many channels as it may */
#define UPS_ERR_FAILED (-11)     /**< Failed: the CAN-ECB could not store it; ask again later */
#define UPS_ERR_REFUSED (-12)    /**< Refuse: the declared stream was not admitted */

/* ---- states (besides the UPS_ERR_ codes that end them) ------------------------------------- */

#define UPS_JOIN_NOT_STARTED 0 /**< ups_join_state(): ups_start() not called yet */
#define UPS_JOIN_JOINING 1     /**< knocking, answering the census, claiming */
#define UPS_JOIN_JOINED 2      /**< the node holds a TxNode (ups_txnode()) */

#define UPS_CHANNEL_FREE 0    /**< ups_channel_state(): no such channel (in use) */
#define UPS_CHANNEL_WAITING 1 /**< asking for its etag, settling, or a publisher's pause */
#define UPS_CHANNEL_BOUND 2   /**< bound: events go and come (ups_publish(), ups_rx()) */

#define UPS_DECL_NONE 0    /**< ups_declaration_state(): the channel has no declaration */
#define UPS_DECL_WAITING 1 /**< its DECLARE goes (again) until an answer stands */
#define UPS_DECL_GRANTED 2 /**< admitted: the channel's priority is the granted one */

/* ---- frames -------------------------------------------------------------------------------- */

#define UPS_FRAME_EXT 0x01u /**< 29-bit identifier (UPS uses no other) */
#define UPS_FRAME_FD 0x02u  /**< CAN FD frame */
#define UPS_FRAME_BRS 0x04u /**< CAN FD bit-rate switch (set on every FD frame this node sends) */
#define UPS_FRAME_RTR 0x08u /**< remote frame (foreign to UPS) */
#define UPS_FRAME_ERR 0x10u /**< error frame (foreign to UPS) */

/** One CAN frame, received or to send. */
typedef struct {
    uint32_t id;             /**< the identifier (29 bits when UPS_FRAME_EXT is set) */
    uint8_t flags;           /**< UPS_FRAME_... */
    uint8_t len;             /**< data bytes: 0..8, or a CAN FD length up to 64 */
    uint8_t data[UPS_MTU];
} ups_frame_t;

/** An acceptance filter: a frame passes when (frame id & mask) == (id & mask), extended only. */
typedef struct {
    uint32_t id;
    uint32_t mask;
} ups_filter_t;

/** One received event. data points into the frame given to ups_rx() (an event of one frame)
 *  or into the node (a transfer's last frame completed it), not into a copy: it is valid until
 *  the next call into the library, and only while that frame is. A port that passes ups_rx() a
 *  slot of the ring its receive interrupt fills must copy the size bytes (or use them) before
 *  it frees the slot to the interrupt; one that pops each frame into a variable first (the
 *  guide's loop) keeps that variable until it is done with the event. */
typedef struct {
    const uint8_t *data;
    uint16_t size;
    uint8_t channel;  /**< the index ups_subscribe() returned */
    uint8_t priority; /**< of the frame(s) it came in */
    uint8_t txnode;   /**< the sender's TxNode */
} ups_event_t;

/** What the library ignored, turned away or gave up, each counted (saturating). */
typedef struct {
    UPS_COUNTER_T foreign;      /**< not UPS: 11-bit, remote, error frames, FD management frames */
    UPS_COUNTER_T malformed;    /**< UPS management frames matching no table row, bad lengths */
    UPS_COUNTER_T unknown;      /**< events on etags this node never saw bound */
    UPS_COUNTER_T filtered;     /**< events on etags bound to channels this node does not receive */
    UPS_COUNTER_T own_echo;     /**< this node's own frames, handed back by the bus */
    UPS_COUNTER_T unbound_dropped; /**< events not sent: the channel's binding was contradicted */
    UPS_COUNTER_T tx_dropped;   /**< frames that did not fit the TX queue */
    UPS_COUNTER_T rebinds;      /**< contradicting or doubted Binds (the channel is bound again) */
    UPS_COUNTER_T moves;        /**< channels moved to a larger size class, or TxNode moves */
    UPS_COUNTER_T large_lost;   /**< transfers given up (broken, stale, evicted, without start) */
} ups_counters_t;

/* ---- notes: what changed since the application last asked (ups_notes) -------------------- */

#define UPS_NOTE_JOINED 0x01u   /**< the node holds a TxNode now (or again, after a move) */
#define UPS_NOTE_JOIN_FAILED 0x02u /**< the join ended: see ups_join_state() */
#define UPS_NOTE_FILTERS 0x04u  /**< program the acceptance filters with ups_filters() now,
                                     before feeding the next frame: raised by ups_start() (the
                                     first programming: the CAN-ECB's frames) and whenever they
                                     change (an etag relied on is received from its Bind on,
                                     so its events may follow the Bind at once) */
#define UPS_NOTE_CHANNELS 0x08u /**< a channel's state changed: see ups_channel_state() */
#define UPS_NOTE_DECLARATIONS 0x10u /**< a declaration's answer stood (granted or refused),
                                         it was given up, or a verdict changed its priority */

/* ---- the node ------------------------------------------------------------------------------ */

/** A channel's entry. Private: read it through the functions below. */
typedef struct {
    uint8_t uid[8];   /* big-endian, as on the wire */
    uint16_t etag;    /* bound, or the candidate while settling; 0: none */
    uint16_t t0;      /* request start / settle start / ready time (low 16 bits of ms) */
    uint8_t flags;    /* UPS__SUB, UPS__PUB, ... (ups_util.h) */
    uint8_t step;     /* wanted size class << 4 | request retry step, or -UPS_ERR_ once failed */
    uint8_t priority; /* for this node's events on the channel */
    uint8_t owe;      /* frames owed to the CAN-ECB: UPS__OWE_... (ups_util.h) */
} ups_channel_t;

#if UPS_DECLARATIONS
typedef struct {
    uint8_t channel;  /* 0xFF: unused */
    int8_t state;     /* UPS_DECL_WAITING, UPS_DECL_GRANTED, or a UPS_ERR_ code */
    uint8_t heard;    /* waiting: 0 DECLARE not sent yet, 1 sent, else the latest verdict since
                         (a granted priority, or 0x80: Refuse), the answer once it stood 0.5 s */
    uint8_t fallback; /* the channel's priority before the declaration (after a Refuse) */
    uint8_t data[8];  /* DECLARE: etag, size, period, deadline, jitter (big-endian) */
} ups_declaration_t; /* its retry, then its verdict wait, run on its channel's timer (free while
                        the channel is bound) */
#endif

#if UPS_WITH_TRANSFERS
typedef struct {
    uint16_t etag;    /* 0: unused */
    uint16_t length;  /* L, the event's size */
    uint16_t got;     /* stream bytes received so far */
    uint16_t crc;     /* CRC of the event bytes received so far */
    uint16_t t_last;  /* when its last frame came */
    uint8_t txnode;
    uint8_t header;   /* tid | the toggle expected next; 0xFF: an orphan run being dropped */
    uint8_t mtu;      /* 8 or 64 */
    uint8_t buf[UPS_MAX_EVENT + 2]; /* the event, then its CRC */
} ups_rx_transfer_t;
#endif

/** The whole state of one node. Private: set up with ups_init(), then use the functions. */
typedef struct {
    uint8_t node_id[8];
    uint8_t txnode;       /* joined: its TxNode; joining: the one last offered to it */
    int8_t join;          /* UPS_JOIN_..., or a UPS_ERR_ code */
    uint8_t notes;
    uint8_t mode;         /* UPS__FD, UPS__OWE_CLAIM, UPS__ANNOUNCE_DUE, UPS__RECENT */
    uint8_t knock_step;
    uint8_t tx_count;
    uint16_t t_join;      /* joining: when it began (for the give-up) */
    uint16_t t_quiet;     /* joining: last Knock sent or heard, or Census/Query/Offer heard;
                             while a refusal is open: it, or the last Hello/Census/Query */
    uint16_t t_announce;  /* joined: when the last answer to Hello started */
    uint16_t t_pace;      /* joined: when its last owed frame was queued */
    uint8_t burst[2][2];  /* Stage answers still to send: {epoch, next stage}; stage 16: none */
    ups_frame_t tx[UPS_TX_DEPTH];
    ups_channel_t channels[UPS_CHANNELS];
#if UPS_DECLARATIONS
    ups_declaration_t decl[UPS_DECLARATIONS];
#endif
#if UPS_HEARD_BINDS
    uint8_t heard_uid[UPS_HEARD_BINDS][8];
    uint16_t heard_etag[UPS_HEARD_BINDS];
    uint8_t heard_next;
#endif
#if UPS_WITH_TRANSFERS
    uint16_t tx_left;     /* stream bytes of the transfer being sent still to queue */
    uint16_t tx_length;
    uint32_t tx_id;
    uint8_t tx_header;
    uint8_t tids[UPS_CHANNELS];  /* the next transfer id per channel */
    uint8_t tx_buf[UPS_MAX_EVENT + 2];
    ups_rx_transfer_t rx[UPS_RX_TRANSFERS];
#endif
    ups_counters_t counters;
} ups_node_t;

/** Bus modes for ups_init(). */
#define UPS_BUS_CLASSIC 0u /**< a classic CAN bus: every frame at most 8 bytes */
#define UPS_BUS_FD 1u      /**< a CAN FD bus: event frames are FD frames with bit-rate switching
                                (needs UPS_WITH_FD); management frames stay classic */

/** Set up @p node with its 64-bit node id (unique on the bus, the same at every start) for a bus
 *  of @p bus_mode (UPS_BUS_CLASSIC or UPS_BUS_FD). The node does nothing until ups_start().
 *  Returns UPS_OK, or UPS_ERR_ARGUMENT (FD without UPS_WITH_FD). */
int ups_init(ups_node_t *node, uint64_t node_id, unsigned bus_mode);

/** Start joining (Knock) at @p now_ms; also after a join that failed. Channels may be added
 *  before or after: their etags are asked for once the node is joined. Raises UPS_NOTE_FILTERS:
 *  program the filters (ups_filters(): the CAN-ECB's frames, and any etag already relied on)
 *  before the Knock it queued goes out, or a controller that accepts nothing after reset never
 *  hears the answer. A joined node stays joined (a move to another TxNode, or the CAN-ECB's
 *  restart, is followed inside the library): calling it then does nothing. */
void ups_start(ups_node_t *node, uint32_t now_ms);

/** Feed one received frame (every frame the controller accepted, in order, own echoes
 *  included). Returns 1 when @p event holds an event for the application, else 0. Frames that
 *  are not UPS, malformed or not for this node are ignored and counted. Read ups_notes() before
 *  feeding the next one (a Bind raises UPS_NOTE_FILTERS). */
int ups_rx(ups_node_t *node, uint32_t now_ms, const ups_frame_t *frame, ups_event_t *event);

/** Run the timers (knock retry, request retry, settling, Hello answers, transfer timeouts) and
 *  queue the frames the node owes the CAN-ECB (requests, SUB_AT/PUB_AT, DECLARE, UNSUB: one at
 *  a time, so that none is lost to a full queue or sent before one it depends on).
 *
 *  How often: every millisecond while the node is busy (ups_idle() is 0), at the latest every
 *  few: each call queues at most one owed frame (the answer to Hello, paced at 1 ms), and a
 *  timer runs at the first call after it fell due. Calls that come less often make timers late,
 *  never early, and lose nothing; but the node keeps each timer's start in 16 bits (a
 *  refusal's in 12, of 4 ms), so a gap longer than 13.4 s (16384 - 3000 ms: a request's
 *  refusal wait) or, while joining, than 65536 ms minus UPS_JOIN_GIVE_UP_MS (35.5 s by default) may make a
 *  timer look just started and run it up to 65.5 s (16.4 s) later still. While ups_idle() is
 *  1 nothing is due: a node that sleeps may stop calling it, for any time, until a frame
 *  arrives or it calls the library again. */
void ups_tick(ups_node_t *node, uint32_t now_ms);

/** The frame to send next (the lowest identifier queued, the first queued among equals), or
 *  NULL. It stays queued until ups_tx_pop(): send it, then pop it (or pop it to drop it), and
 *  call nothing else of the library in between (a call may queue a frame before it, or drop
 *  it: a contradicted binding drops what was queued on its etag). */
const ups_frame_t *ups_tx_peek(const ups_node_t *node);

/** Remove the frame ups_tx_peek() returned (it was sent). A request counts as sent from here:
 *  only Binds fed after this call may answer it (docs/protocol.md, "Binding"). */
void ups_tx_pop(ups_node_t *node);

/** What happened since the last call (UPS_NOTE_... bits), cleared by the call. Read it after
 *  ups_start() and after each ups_rx() and ups_tick(): UPS_NOTE_FILTERS wants the filters
 *  programmed before the next frame is fed. */
unsigned ups_notes(ups_node_t *node);

/** Whether nothing is due: 1 when the node is not joining, has no frame queued or owed (an
 *  answer to Hello, a request, SUB_AT, PUB_AT, DECLARE, UNSUB), no channel or declaration
 *  waiting for an answer, no Hello answered within the last second and no transfer half sent
 *  or half received; else 0. A node that sleeps ticks every millisecond while it is 0. */
int ups_idle(const ups_node_t *node);

/** The join: UPS_JOIN_NOT_STARTED, UPS_JOIN_JOINING, UPS_JOIN_JOINED, or UPS_ERR_TIMEOUT,
 *  UPS_ERR_TXNODES_FULL, UPS_ERR_FAILED when it ended (call ups_start() again). Anyone can send
 *  TxNodesFull or Failed: one naming this node's id ends the join only once it stood 3 s (the
 *  refusal wait, counted again from each Hello, Census or Query heard after it) with no Offer
 *  or Assign of the id; meanwhile the node does not knock. A join that reaches
 *  UPS_JOIN_GIVE_UP_MS with one open ends with its error. */
int ups_join_state(const ups_node_t *node);

/** This node's TxNode (0..126), or -1 while it holds none. */
int ups_txnode(const ups_node_t *node);

/** Subscribe to channel @p uid. Returns the channel's index (the same for every role of one
 *  UID), or UPS_ERR_FULL. The node asks for the etag (SUB_BIND) at the next ups_tick() once
 *  joined (again, if the channel was waiting for an answer to another request: that answer
 *  would not tell the CAN-ECB of the subscription). @p now_ms is not read: the request's timers
 *  start when ups_tick() queues it, so any value will do (pass the clock). */
int ups_subscribe(ups_node_t *node, uint64_t uid, uint32_t now_ms);

/** Publish on channel @p uid events of up to @p max_size bytes (its size class follows: PUB_BIND
 *  for 8 bytes or fewer, PUB_BIND(c) above; calling it again with larger events moves the
 *  channel to their class). Returns the channel's index, UPS_ERR_FULL, or UPS_ERR_TOO_LARGE
 *  (above UPS_MAX_EVENT). Asked, like ups_subscribe(), at the next ups_tick(); @p now_ms is not
 *  read either. */
int ups_advertise(ups_node_t *node, uint64_t uid, uint16_t max_size, uint32_t now_ms);

/** Stop receiving channel @p channel: UNSUB goes at a next ups_tick(). A channel nobody
 *  publishes on is freed once its UNSUB is queued (ups_subscribe() to it meanwhile takes it
 *  back, and no UNSUB goes). UPS_OK, or UPS_ERR_ARGUMENT (no such channel). */
int ups_unsubscribe(ups_node_t *node, int channel);

/** Queue one event of @p size bytes on @p channel (copied: the buffer is free on return).
 *  UPS_OK, or UPS_ERR_UNBOUND (no etag relied on yet, or being bound again), UPS_ERR_TOO_LARGE,
 *  UPS_ERR_FULL (queue full: counted in tx_dropped), UPS_ERR_BUSY (a transfer of several
 *  frames is being queued, or, for a transfer, frames of this channel queued at another
 *  priority still wait: the frames of one etag go in order). */
int ups_publish(ups_node_t *node, int channel, const uint8_t *data, uint16_t size);

/** Set the priority of this node's events on @p channel: 0x02..0xFF (default 0x80; 0x00 and
 *  0x01 are management: given 0 or 1, the node uses 0x02). A Grant sets it too. UPS_OK, or
 *  UPS_ERR_ARGUMENT (no such channel). */
int ups_set_priority(ups_node_t *node, int channel, uint8_t priority);

/** The priority this node's events on @p channel go at now (0x02..0xFF): the default 0x80,
 *  ups_set_priority()'s, or the one a Grant gave (read it on UPS_NOTE_DECLARATIONS), or
 *  UPS_ERR_ARGUMENT (no such channel). */
int ups_channel_priority(const ups_node_t *node, int channel);

/** A channel's state: UPS_CHANNEL_FREE, UPS_CHANNEL_WAITING (for its etag, or being bound
 *  again, or a publisher's 150 ms pause on a larger size class), UPS_CHANNEL_BOUND (events may
 *  go: ups_publish()), or a UPS_ERR_ code (the request ended:
 *  UPS_ERR_TIMEOUT, UPS_ERR_ETAGS_FULL, UPS_ERR_LIMIT, UPS_ERR_FAILED, UPS_ERR_TOO_LARGE).
 *  EtagsFull, Limit and Failed are refusals, and anyone can send them: the node keeps asking,
 *  and one ends the request only once it stood 3 s with no Bind answering the request while
 *  the node kept asking (or when the request gives up after 5 s with one open); one heard
 *  before the request went answers nothing. A Bind answering a subscription with an
 *  etag of a size class whose events would not fit the node (UPS_MAX_EVENT; without transfers,
 *  any class above 0) is taken the same way: anyone can send it too, and a Bind that fits, the
 *  CAN-ECB's answer, wins; once it stood, the node sends UNSUB and the state is
 *  UPS_ERR_TOO_LARGE, or, on a channel it also publishes on, it stops receiving it and asks
 *  again as a publisher. A channel being bound again after a contradiction takes neither: it
 *  keeps asking until a Bind binds it (forged frames cannot end a channel the node had bound;
 *  nor can a real move of the channel to a class the node cannot receive: it keeps asking, and
 *  counts the move; ups_unsubscribe() ends it). */
int ups_channel_state(const ups_node_t *node, int channel);

/** The etag @p channel is bound to and relied on, or 0 (also during its re-binding). */
uint16_t ups_channel_etag(const ups_node_t *node, int channel);

/** Write the acceptance filters the node needs into @p out (at most @p max) and return how
 *  many it needs: one for the CAN-ECB's frames, one per received etag. When it needs more than
 *  @p max, accept every extended frame instead: the library filters in software. */
int ups_filters(const ups_node_t *node, ups_filter_t *out, int max);

/** Declare @p channel (published on, in state UPS_CHANNEL_BOUND) a real-time stream: at most
 *  one event of @p size bytes (frames per event on a larger size class) every @p period,
 *  released up to @p jitter late, due within @p deadline; times in units of 100 us. Sends
 *  DECLARE (request retry, 5 s) until it hears Grant or Refuse for it. The answer is the
 *  latest verdict heard since the DECLARE went (ups_tx_pop), once it stood 0.5 s with no other
 *  (the verdict wait: the CAN-ECB corrects a forged one at once); until then the channel keeps
 *  its priority. Only verdicts for a stream the node declared count (its DECLARE sent, its
 *  answer not a Refuse); for one, a Grant sets the priority (also unasked: read it with
 *  ups_channel_priority()) and a Refuse puts back the priority from before ups_declare(),
 *  until a Grant.
 *  A stream stays declared for the node's life: the node sends its DECLARE again by itself in
 *  every answer to Hello (the CAN-ECB restarted, or it moved the node to another TxNode, or
 *  assigned it its own again) while the state is UPS_DECL_WAITING or UPS_DECL_GRANTED and the
 *  channel is bound. Call ups_declare() again only after ups_init() (a reset), to change the
 *  stream, or once it ended (UPS_ERR_REFUSED, UPS_ERR_TIMEOUT).
 *  Returns UPS_OK, UPS_ERR_ARGUMENT (no such published channel, a period or deadline of 0, a
 *  size out of range), UPS_ERR_UNBOUND (not bound) or UPS_ERR_FULL (UPS_DECLARATIONS
 *  streams declared already, or none compiled in). */
int ups_declare(ups_node_t *node, int channel, uint8_t size, uint16_t period, uint16_t deadline,
                uint8_t jitter, uint32_t now_ms);

/** The declaration of @p channel: UPS_DECL_NONE, UPS_DECL_WAITING (for its answer),
 *  UPS_DECL_GRANTED (its priority is the channel's, ups_channel_priority(); a later Refuse puts
 *  the channel back to its former priority until a Grant comes), UPS_ERR_REFUSED (the answer
 *  was Refuse: the declaration is over) or UPS_ERR_TIMEOUT (no verdict within 5 s; a later
 *  Grant still makes it UPS_DECL_GRANTED). */
int ups_declaration_state(const ups_node_t *node, int channel);

/** The counters (read-only; they saturate). */
const ups_counters_t *ups_counters(const ups_node_t *node);

#ifdef __cplusplus
}
#endif
#endif /* UPS_H */
