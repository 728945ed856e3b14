/*
 * libups-ecb: what every source stands on (byte helpers, counters, the TX queue). It calls no
 * other source of the library.
 */
#include "ups_ecb_internal.h"

void ups_ecb__count(UPS_ECB_COUNTER_T *counter)
{
    if (*counter < (UPS_ECB_COUNTER_T)~(UPS_ECB_COUNTER_T)0u) {
        ++*counter;
    }
}

void ups_ecb__note(ups_ecb_t *ecb, unsigned bits)
{
    ecb->notes = (uint8_t)(ecb->notes | bits);
}

int ups_ecb__same8(const uint8_t *a, const uint8_t *b)
{
    unsigned diff = 0;
    for (unsigned i = 0; i < 8u; i++) {
        diff |= (unsigned)(a[i] ^ b[i]);
    }
    return diff == 0u;
}

void ups_ecb__copy(uint8_t *to, const uint8_t *from, unsigned n)
{
    for (unsigned i = 0; i < n; i++) {
        to[i] = from != NULL ? from[i] : 0u;
    }
}

uint64_t ups_ecb__get64(const uint8_t *in)
{
    uint64_t value = 0;
    for (unsigned i = 0; i < 8u; i++) {
        value = (value << 8) | in[i];
    }
    return value;
}

void ups_ecb__put64(uint8_t *out, uint64_t value)
{
    for (unsigned i = 8u; i-- > 0u;) {
        out[i] = (uint8_t)value;
        value >>= 8;
    }
}

/** tx[to] = tx[from] and its length, by the byte helper (a struct assignment in a loop becomes
 *  memmove). */
static void shift(ups_ecb_t *ecb, unsigned to, unsigned from)
{
    ups_ecb__copy((uint8_t *)&ecb->tx[to], (const uint8_t *)&ecb->tx[from],
                  (unsigned)sizeof(ecb->tx[0]));
    ecb->tx_len[to] = ecb->tx_len[from];
}

/** tx_head: the first frame of the queue, as ups_ecb_tx_peek() hands it out. */
static void head(ups_ecb_t *ecb)
{
    if (ecb->tx_count == 0u) {
        return;
    }
    ecb->tx_head.id = ecb->tx[0].id;
    ecb->tx_head.flags = UPS_FRAME_EXT;
    ecb->tx_head.len = ecb->tx_len[0];
    ups_ecb__copy(ecb->tx_head.data, ecb->tx[0].data, 8u);
}

void ups_ecb__send(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    if (ecb->tx_count >= UPS_ECB_TX_DEPTH) {
        ups_ecb__count(&ecb->counters.tx_dropped);
        return;
    }
    unsigned at = ecb->tx_count;
    while (at > 0u && ecb->tx[at - 1u].id > id) { /* after its equals: FIFO among them */
        shift(ecb, at, at - 1u);
        at--;
    }
    ups_ecb_frame_t *frame = &ecb->tx[at];
    frame->id = id;
    ecb->tx_len[at] = (uint8_t)len;
    ups_ecb__copy(frame->data, data, len);
    ecb->tx_count++;
    if (at == 0u) {
        head(ecb);
    }
}

void ups_ecb__pop(ups_ecb_t *ecb)
{
    if (ecb->tx_count == 0u) {
        return;
    }
    for (unsigned i = 1u; i < ecb->tx_count; i++) {
        shift(ecb, i - 1u, i);
    }
    ecb->tx_count--;
    head(ecb);
}

void ups_ecb__send8(ups_ecb_t *ecb, unsigned field, const uint8_t *data)
{
    ups_ecb__send(ecb, ups_ecb__id(0u, UPS_ECB__MGMT, field), data, data != NULL ? 8u : 0u);
}

uint32_t ups_ecb__age(uint32_t now, uint32_t *then)
{
    uint32_t age = ups_ecb__since(now, *then);
    if (age > UPS_ECB__AGE_MAX) {
        *then = now - UPS_ECB__AGE_MAX;
        age = UPS_ECB__AGE_MAX;
    }
    return age;
}

uint32_t ups_ecb__crc32(uint32_t crc, const uint8_t *data, size_t n)
{
    crc = ~crc;
    for (size_t i = 0; i < n; i++) {
        crc ^= data[i];
        for (unsigned k = 0; k < 8u; k++) {
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
        }
    }
    return ~crc;
}
