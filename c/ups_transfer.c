/*
 * libups: events larger than one frame (docs/protocol.md, "Events larger than one frame").
 *
 * A transfer's frames each start with a header byte S E T tid; the bytes after the headers form
 * the stream: the event's length L (u16), the event, and, when the transfer has more than one
 * frame, the CRC-16/CCITT-FALSE of the event. Every frame but the last is full (8 bytes, or 64
 * on CAN FD); on FD the last is padded with zeros to a CAN FD length.
 *
 * Sending: one transfer at a time; its bytes are copied into the node and its frames queued as
 * room appears in the TX queue. Receiving: one transfer in progress per (TxNode, etag), in
 * UPS_RX_TRANSFERS slots; anything that cannot be an intact event is counted in large_lost.
 */
#include "ups_transfer.h"
#include "ups_util.h"

#if UPS_WITH_TRANSFERS

#define T_START 0x80u
#define T_END 0x40u
#define T_TOGGLE 0x20u
#define T_TID 0x1Fu
#define ORPHAN 0x40u /* in a slot's header: a run of frames whose start never came */
#define TRANSFER_TIMEOUT 1000u

static uint16_t crc16(const uint8_t *data, unsigned n)
{
    uint16_t crc = 0xFFFFu;
    for (unsigned i = 0; i < n; ++i) {
        crc = (uint16_t)(crc ^ ((unsigned)data[i] << 8));
        for (unsigned bit = 0; bit < 8u; ++bit) {
            crc = (uint16_t)((crc & 0x8000u) ? ((unsigned)crc << 1) ^ 0x1021u : (unsigned)crc << 1);
        }
    }
    return crc;
}

/** The CAN FD data length that carries @p n bytes. */
static unsigned fd_length(unsigned n)
{
    static const uint8_t sizes[7] = {12u, 16u, 20u, 24u, 32u, 48u, 64u};
    unsigned i = 0u;
    if (n <= 8u) {
        return n;
    }
    while (i < 6u && sizes[i] < n) {
        ++i;
    }
    return sizes[i];
}

static inline unsigned node_mtu(const ups_node_t *node)
{
    return (node->mode & UPS__FD) ? 64u : 8u;
}

static inline uint8_t event_flags(const ups_node_t *node)
{
    return (node->mode & UPS__FD) ? (uint8_t)(UPS_FRAME_FD | UPS_FRAME_BRS) : 0u;
}

/* ---- sending ------------------------------------------------------------------------------- */

/** Whether a transfer with identifier @p id must wait: the frames of one etag go in order, so
 *  it may start neither while the transfer being queued is on its etag (or is any other
 *  transfer of several frames: there is one transmit buffer), nor while frames of its etag
 *  with another identifier wait in the queue (the channel's priority changed: they would be
 *  overtaken, and the receiver would take the new first frame as the end of the old
 *  transfer). */
static int must_wait(const ups_node_t *node, uint32_t id, int several)
{
    if (node->tx_left > 0u && (several || ((node->tx_id ^ id) & UPS__ETAG_MASK) == 0u)) {
        return 1;
    }
    for (unsigned i = 0; i < node->tx_count; ++i) {
        if (((node->tx[i].id ^ id) & UPS__ETAG_MASK) == 0u && node->tx[i].id != id) {
            return 1;
        }
    }
    return 0;
}

int ups__transfer_tx(ups_node_t *node, int channel, uint32_t id, const uint8_t *data,
                     uint16_t size)
{
    if (size > ups__class_max(ups__class(id & UPS__ETAG_MASK)) || size > UPS_MAX_EVENT) {
        return UPS_ERR_TOO_LARGE;
    }
    unsigned chunk = node_mtu(node) - 1u;
    if (must_wait(node, id, 2u + size > chunk)) {
        return UPS_ERR_BUSY;
    }
    unsigned tid = node->tids[channel] & T_TID;
    node->tids[channel] = (uint8_t)((tid + 1u) & T_TID);
    if (2u + size <= chunk) { /* one frame, no CRC: the frame's own guards it */
        uint8_t frame[UPS_MTU];
        unsigned len = 3u + size;
        unsigned padded = node_mtu(node) > 8u ? fd_length(len) : len;
        frame[0] = (uint8_t)(T_START | T_END | T_TOGGLE | tid);
        frame[1] = (uint8_t)(size >> 8);
        frame[2] = (uint8_t)size;
        ups__copy(frame + 3, data, size);
        ups__copy(frame + len, NULL, padded - len);
        return ups__push(node, id, event_flags(node), frame, padded);
    }
    uint16_t crc = crc16(data, size);
    ups__copy(node->tx_buf, data, size);
    node->tx_buf[size] = (uint8_t)(crc >> 8);
    node->tx_buf[size + 1u] = (uint8_t)crc;
    node->tx_length = size;
    node->tx_left = (uint16_t)(size + 4u);
    node->tx_id = id;
    node->tx_header = (uint8_t)(T_TOGGLE | tid);
    ups__transfer_refill(node);
    return UPS_OK;
}

void ups__transfer_refill(ups_node_t *node)
{
    unsigned chunk = node_mtu(node) - 1u;
    unsigned total = node->tx_length + 4u;
    while (node->tx_left > 0u && node->tx_count < UPS__EVENT_ROOM) {
        uint8_t frame[UPS_MTU];
        unsigned at = total - node->tx_left;
        unsigned n = node->tx_left < chunk ? node->tx_left : chunk;
        unsigned header = node->tx_header;
        if (at == 0u) {
            header |= T_START;
        }
        if (node->tx_left <= chunk) {
            header |= T_END;
        }
        frame[0] = (uint8_t)header;
        for (unsigned i = 0; i < n; ++i) {
            unsigned p = at + i;
            frame[1u + i] = p == 0u   ? (uint8_t)(node->tx_length >> 8)
                            : p == 1u ? (uint8_t)node->tx_length
                                      : node->tx_buf[p - 2u];
        }
        unsigned len = 1u + n;
        unsigned padded = node_mtu(node) > 8u ? fd_length(len) : len;
        ups__copy(frame + len, NULL, padded - len);
        (void)ups__push(node, node->tx_id, event_flags(node), frame, padded);
        node->tx_left = (uint16_t)(node->tx_left - n);
        node->tx_header = (uint8_t)(node->tx_header ^ T_TOGGLE);
    }
}

/* ---- receiving ----------------------------------------------------------------------------- */

/** A frame's data holds @p used stream bytes (header included) and then nothing, or on FD the
 *  zeros that pad it to a CAN FD length. */
static int tail_ok(const uint8_t *data, unsigned used, unsigned len, unsigned mtu)
{
    if (len < used) {
        return 0;
    }
    if (len == used) {
        return mtu == 8u || len == fd_length(len);
    }
    if (mtu != 64u || len != fd_length(len)) {
        return 0;
    }
    for (unsigned i = used; i < len; ++i) {
        if (data[i] != 0u) {
            return 0;
        }
    }
    return 1;
}

static ups_rx_transfer_t *slot_of(ups_node_t *node, uint8_t txnode, uint16_t etag)
{
    for (unsigned i = 0; i < UPS_RX_TRANSFERS; ++i) {
        if (node->rx[i].etag == etag && node->rx[i].txnode == txnode) {
            return &node->rx[i];
        }
    }
    return NULL;
}

/** A free slot, or one only marking an orphan run; with @p evict, else the oldest (lost). */
static ups_rx_transfer_t *new_slot(ups_node_t *node, uint32_t now, int evict)
{
    ups_rx_transfer_t *oldest = NULL;
    for (unsigned i = 0; i < UPS_RX_TRANSFERS; ++i) {
        ups_rx_transfer_t *slot = &node->rx[i];
        if (slot->etag == 0u || (slot->header & ORPHAN)) {
            return slot;
        }
        if (oldest == NULL || ups__since(now, slot->t_last) > ups__since(now, oldest->t_last)) {
            oldest = slot;
        }
    }
    if (evict && oldest != NULL) {
        ups__count(&node->counters.large_lost);
    }
    return evict ? oldest : NULL;
}

/** A frame without S that belongs to no transfer: dropped; each run (one tid) is one loss. */
static void orphan(ups_node_t *node, ups_rx_transfer_t *slot, uint8_t txnode, uint16_t etag,
                   unsigned tid, uint32_t now)
{
    if (slot != NULL && slot->header == (ORPHAN | tid)) {
        slot->t_last = now16(now);
        return;
    }
    ups__count(&node->counters.large_lost);
    if (slot == NULL) {
        slot = new_slot(node, now, 0);
    }
    if (slot != NULL) {
        slot->etag = etag;
        slot->txnode = txnode;
        slot->header = (uint8_t)(ORPHAN | tid);
        slot->t_last = now16(now);
    }
}

static int start(ups_node_t *node, const ups_frame_t *frame, uint8_t txnode, uint16_t etag,
                 uint32_t now, ups_event_t *event)
{
    unsigned mtu = (frame->flags & UPS_FRAME_FD) ? 64u : 8u;
    unsigned len = frame->len;
    const uint8_t *data = frame->data;
    uint32_t largest = ups__class_max(ups__class(etag));
    unsigned length = len >= 3u ? ((unsigned)data[1] << 8) | data[2] : 0xFFFFFFu;
    int single = 2u + length <= mtu - 1u;
    if (!(data[0] & T_TOGGLE) || length > largest || length > UPS_MAX_EVENT ||
        single != ((data[0] & T_END) != 0u) || (!single && len != mtu)) {
        ups__count(&node->counters.large_lost);
        return 0;
    }
    if (single) {
        if (!tail_ok(data, 3u + length, len, mtu)) {
            ups__count(&node->counters.large_lost);
            return 0;
        }
        event->data = data + 3;
        event->size = (uint16_t)length;
        return 1;
    }
    ups_rx_transfer_t *slot = new_slot(node, now, 1);
    if (slot == NULL) {
        return 0; /* unreachable: UPS_RX_TRANSFERS >= 1 */
    }
    slot->etag = etag;
    slot->txnode = txnode;
    slot->length = (uint16_t)length;
    slot->got = (uint16_t)(len - 1u);
    slot->header = (uint8_t)(data[0] & T_TID); /* the next frame has no toggle */
    slot->mtu = (uint8_t)mtu;
    slot->t_last = now16(now);
    ups__copy(slot->buf, data + 3, len - 3u);
    return 0;
}

int ups__transfer_rx(ups_node_t *node, uint32_t now, const ups_frame_t *frame, uint8_t txnode,
                     uint16_t etag, ups_event_t *event)
{
    ups_rx_transfer_t *slot = slot_of(node, txnode, etag);
    unsigned len = frame->len;
    const uint8_t *data = frame->data;
    if (len == 0u) {
        orphan(node, slot, txnode, etag, T_TOGGLE, now);
        return 0;
    }
    unsigned header = data[0];
    unsigned tid = header & T_TID;
    if (header & T_START) {
        if (slot != NULL) {
            if (!(slot->header & ORPHAN)) {
                ups__count(&node->counters.large_lost); /* a new start ends the one in progress */
            }
            slot->etag = 0u;
        }
        return start(node, frame, txnode, etag, now, event);
    }
    if (slot == NULL || (slot->header & ORPHAN)) {
        orphan(node, slot, txnode, etag, tid, now);
        return 0;
    }
    unsigned mtu = slot->mtu;
    unsigned total = slot->length + 4u;
    unsigned need = total - slot->got;
    int last = need <= mtu - 1u;
    if (tid != (slot->header & T_TID) || (header & T_TOGGLE) != (slot->header & T_TOGGLE) ||
        last != ((header & T_END) != 0u) || mtu != ((frame->flags & UPS_FRAME_FD) ? 64u : 8u) ||
        (!last && len != mtu) || (last && !tail_ok(data, 1u + need, len, mtu))) {
        ups__count(&node->counters.large_lost); /* the event is lost, never delivered in part */
        if (tid != (slot->header & T_TID)) {
            ups__count(&node->counters.large_lost); /* and a run without its start begins */
        }
        slot->header = (uint8_t)(ORPHAN | tid);
        slot->t_last = now16(now);
        return 0;
    }
    unsigned n = last ? need : len - 1u;
    ups__copy(slot->buf + (slot->got - 2u), data + 1, n);
    slot->got = (uint16_t)(slot->got + n);
    slot->header = (uint8_t)(slot->header ^ T_TOGGLE);
    slot->t_last = now16(now);
    if (!last) {
        return 0;
    }
    slot->etag = 0u; /* done: the slot is free, its buffer valid until the next call */
    unsigned size = slot->length;
    if (crc16(slot->buf, size) != (((unsigned)slot->buf[size] << 8) | slot->buf[size + 1u])) {
        ups__count(&node->counters.large_lost);
        return 0;
    }
    event->data = slot->buf;
    event->size = (uint16_t)size;
    return 1;
}

void ups__transfer_tick(ups_node_t *node, uint32_t now)
{
    for (unsigned i = 0; i < UPS_RX_TRANSFERS; ++i) {
        ups_rx_transfer_t *slot = &node->rx[i];
        if (slot->etag != 0u && ups__since(now, slot->t_last) > TRANSFER_TIMEOUT) {
            if (!(slot->header & ORPHAN)) {
                ups__count(&node->counters.large_lost); /* its next frame did not come */
            }
            slot->etag = 0u;
        }
    }
}

void ups__transfer_drop(ups_node_t *node, uint16_t etag)
{
    if ((node->tx_id & UPS__ETAG_MASK) == etag) {
        node->tx_left = 0u;
    }
    for (unsigned i = 0; i < UPS_RX_TRANSFERS; ++i) {
        ups_rx_transfer_t *slot = &node->rx[i];
        if (slot->etag == etag) {
            if (!(slot->header & ORPHAN)) {
                ups__count(&node->counters.large_lost);
            }
            slot->etag = 0u;
        }
    }
}

#else
typedef int ups_transfer_unused; /* ISO C forbids an empty translation unit */
#endif
