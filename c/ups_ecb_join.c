/*
 * libups-ecb: TxNodes by node id, the census (Knock, Census, Query, Stage), Offers, CLAIM,
 * Assign, moves, TxNodesFull. SKELETON: to be completed by its owner.
 */
#include "ups_ecb_internal.h"

void ups_ecb__join_init(ups_ecb_t *ecb)
{
    for (unsigned i = 0; i < UPS_ECB_NODES; i++) {
        ecb->join.nodes[i].txnode = 0xFFu;
    }
}

int ups_ecb__holder(const ups_ecb_t *ecb, unsigned txnode)
{
    for (int i = 0; i < UPS_ECB_NODES; i++) {
        if (ecb->join.nodes[i].txnode == txnode) {
            return i;
        }
    }
    return UPS_ECB__NO_SLOT;
}

void ups_ecb__join_rx(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    (void)ecb;
    (void)id;
    (void)data;
    (void)len;
}

void ups_ecb__join_tick(ups_ecb_t *ecb)
{
    (void)ecb;
}

void ups_ecb__join_stop(ups_ecb_t *ecb)
{
    (void)ecb;
}

int ups_ecb__join_busy(const ups_ecb_t *ecb)
{
    (void)ecb;
    return 0;
}

void ups_ecb__join_recovered(ups_ecb_t *ecb)
{
    (void)ecb;
}

size_t ups_ecb__join_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    (void)ecb;
    (void)out;
    (void)cap;
    return 0u;
}

int ups_ecb__join_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size)
{
    (void)ecb;
    (void)in;
    (void)size;
    return UPS_ERR_ARGUMENT;
}
