/*
 * libups: what every source stands on (see ups_util.h for each call): size classes, byte
 * helpers, the saturating counters and the TX queue. Nothing here calls into another source:
 * ups.c (receiving, the timers, the API), ups_join.c, ups_bind.c and ups_transfer.c call down
 * into this file, never the other way.
 */
#include "ups_util.h"

/* ---- size classes, bytes and counters ------------------------------------------------------ */

unsigned ups__class(unsigned etag)
{
    return etag < UPS__LARGE_ETAG ? 0u : 1u + ((unsigned)(etag - UPS__LARGE_ETAG) >> 10);
}

uint32_t ups__class_max(unsigned cls)
{
    static const uint32_t largest[5] = {8u, 64u, 1024u, 4096u, 65535u};
    return largest[cls < 5u ? cls : 4u];
}

/* The library calls no C library function, and a -nostdlib link has none. A loop that stores
 * contiguous bytes is what compilers turn into a call of memcpy or memset (gcc from -Os up
 * without -ffreestanding or -fno-tree-loop-distribute-patterns, clang without -ffreestanding):
 * this one stores every other byte in each of two passes, which neither call does. */
void ups__copy(uint8_t *to, const uint8_t *from, unsigned n)
{
    for (unsigned start = 0; start < 2u; ++start) {
        for (unsigned i = start; i < n; i += 2u) {
            to[i] = from != NULL ? from[i] : 0u;
        }
    }
}

void ups__count(UPS_COUNTER_T *counter)
{
    if (*counter < (UPS_COUNTER_T)~(UPS_COUNTER_T)0u) {
        ++*counter;
    }
}

int ups__same8(const uint8_t *a, const uint8_t *b)
{
    unsigned diff = 0;
    for (unsigned i = 0; i < 8u; ++i) {
        diff |= (unsigned)(a[i] ^ b[i]);
    }
    return diff == 0u;
}

unsigned ups__nibble(const uint8_t *id, unsigned stage)
{
    unsigned byte = id[stage >> 1];
    return (stage & 1u) ? (byte & 0xFu) : (byte >> 4);
}

void ups__put64(uint8_t *out, uint64_t value)
{
    for (unsigned i = 8u; i-- > 0u;) {
        out[i] = (uint8_t)value;
        value >>= 8;
    }
}

/* ---- the TX queue -------------------------------------------------------------------------- */

/** tx[to] = tx[from], byte by byte (a struct copy would call memcpy). */
static void move_frame(ups_node_t *node, unsigned to, unsigned from)
{
    ups__copy((uint8_t *)&node->tx[to], (const uint8_t *)&node->tx[from], sizeof(ups_frame_t));
}

int ups__push(ups_node_t *node, uint32_t id, uint8_t flags, const uint8_t *data, unsigned len)
{
    unsigned at = node->tx_count;
    if (at >= (id >= UPS__FIRST_EVENT_ID ? UPS__EVENT_ROOM : UPS_TX_DEPTH)) {
        ups__count(&node->counters.tx_dropped);
        return UPS_ERR_FULL;
    }
    node->tx_count = (uint8_t)(at + 1u);
    while (at > 0u && node->tx[at - 1u].id > id) {
        move_frame(node, at, at - 1u);
        --at;
    }
    node->tx[at].id = id; /* indexed, not through a pointer: -fsanitize=bounds checks it */
    node->tx[at].flags = (uint8_t)(flags | UPS_FRAME_EXT);
    node->tx[at].len = (uint8_t)len; /* at most UPS_MTU: every caller sees to it */
    ups__copy(node->tx[at].data, data, len);
    return UPS_OK;
}

void ups__push_request(ups_node_t *node, unsigned priority, unsigned etag, const uint8_t *data)
{
    (void)ups__push(node, ups__make_id(priority, node->txnode, etag), 0u, data, 8u);
}

void ups__tx_drop(ups_node_t *node, unsigned first, unsigned etag)
{
    unsigned kept = 0u;
    for (unsigned i = first; i < node->tx_count; ++i) {
        if ((node->tx[i].id & UPS__ETAG_MASK) != etag) { /* requests: etags below 0x10 */
            move_frame(node, kept++, i);
        }
    }
    node->tx_count = (uint8_t)kept;
}
