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
    for (unsigned i = 8u; i-- > 0u;) { /* the last byte first: ids and UIDs of one bus */
        if (a[i] != b[i]) {            /* mostly share their first ones */
            return 0;
        }
    }
    return 1;
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

/** tx_head: the frame to send first (the lowest identifier, the first queued among equals:
 *  the queue keeps the order the frames came in, so that queuing one moves none), as
 *  ups_ecb_tx_peek() hands it out; returns its entry. */
static unsigned head(ups_ecb_t *ecb)
{
    const ups_ecb_frame_t *tx = ecb->tx;
    unsigned at = 0u;
    for (unsigned i = 1u; i < ecb->tx_count; i++) {
        if (tx[i].id < tx[at].id) {
            at = i;
        }
    }
    ups_frame_t *h = &ecb->tx_head;
    h->id = tx[at].id;
    h->flags = UPS_FRAME_EXT;
    h->len = ecb->tx_len[at];
    ups_ecb__copy(h->data, tx[at].data, 8u);
    return at;
}

void ups_ecb__send(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    unsigned n = ecb->tx_count;
    if (n >= UPS_ECB_TX_DEPTH) {
        ups_ecb__count(&ecb->counters.tx_dropped);
        return;
    }
    ecb->tx[n].id = id;
    ecb->tx_len[n] = (uint8_t)len;
    ups_ecb__copy(ecb->tx[n].data, len != 0u ? data : NULL, 8u); /* no data: zeros */
    ecb->tx_count = (uint8_t)(n + 1u);
    (void)head(ecb);
}

void ups_ecb__pop(ups_ecb_t *ecb)
{
    unsigned n = ecb->tx_count;
    if (n == 0u) {
        return;
    }
    unsigned at = head(ecb);
    unsigned after = n - 1u - at; /* the entries behind it move up one */
    uint8_t *frame = (uint8_t *)&ecb->tx[at];
    uint8_t *len = &ecb->tx_len[at];
    ups_ecb__copy(frame, frame + sizeof(ecb->tx[0]), after * (unsigned)sizeof(ecb->tx[0]));
    ups_ecb__copy(len, len + 1, after);
    ecb->tx_count = (uint8_t)(n - 1u);
    (void)head(ecb);
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
