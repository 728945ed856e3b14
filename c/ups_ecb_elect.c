/*
 * libups-ecb: the election among the CAN-ECBs of a bus (docs/protocol.md, "More than one
 * CAN-ECB"): Hello, Serving, Probe, candidacy, takeover, the watch of unanswered requests.
 * SKELETON: to be completed by its owner.
 */
#include "ups_ecb_internal.h"

void ups_ecb__elect_start(ups_ecb_t *ecb)
{
    ecb->elect.role = UPS_ECB_SERVING;
}

unsigned ups_ecb__elect_heard(ups_ecb_t *ecb, unsigned status, const uint8_t *instance,
                              uint32_t id, const uint8_t *data, int busy)
{
    (void)ecb;
    (void)status;
    (void)instance;
    (void)id;
    (void)data;
    (void)busy;
    return 0u;
}

unsigned ups_ecb__elect_asked(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    (void)ecb;
    (void)id;
    (void)data;
    (void)len;
    return 0u;
}

unsigned ups_ecb__elect_tick(ups_ecb_t *ecb)
{
    (void)ecb;
    return 0u;
}
