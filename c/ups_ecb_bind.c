/*
 * libups-ecb: etags by UID (size classes, the contradiction rule, EtagsFull, Limit, the quota,
 * leases), who uses which channel (SUB_BIND, PUB_BIND, UNSUB, SUB_AT, PUB_AT), requests held
 * in the recovery window, the Roster's answers, and declared streams (DECLARE, Grant, Refuse,
 * by ups_ecb_rt.c). SKELETON: to be completed by its owner.
 */
#include "ups_ecb_internal.h"

void ups_ecb__bind_init(ups_ecb_t *ecb)
{
    (void)ecb;
}

void ups_ecb__bind_request(ups_ecb_t *ecb, int slot, uint32_t id, const uint8_t *data)
{
    (void)ecb;
    (void)slot;
    (void)id;
    (void)data;
}

void ups_ecb__bind_event(ups_ecb_t *ecb, unsigned etag)
{
    (void)ecb;
    (void)etag;
}

void ups_ecb__bind_forget(ups_ecb_t *ecb, int slot)
{
    (void)ecb;
    (void)slot;
}

void ups_ecb__bind_correct(ups_ecb_t *ecb, uint32_t id, const uint8_t *data, unsigned len)
{
    (void)ecb;
    (void)id;
    (void)data;
    (void)len;
}

void ups_ecb__bind_recovered(ups_ecb_t *ecb)
{
    (void)ecb;
}

void ups_ecb__bind_stop(ups_ecb_t *ecb)
{
    (void)ecb;
}

void ups_ecb__bind_tick(ups_ecb_t *ecb)
{
    (void)ecb;
}

size_t ups_ecb__bind_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    (void)ecb;
    (void)out;
    (void)cap;
    return 0u;
}

int ups_ecb__bind_restore(ups_ecb_t *ecb, const uint8_t *in, size_t size)
{
    (void)ecb;
    (void)in;
    (void)size;
    return UPS_ERR_ARGUMENT;
}

int ups_ecb_channel_use(const ups_ecb_t *ecb, int i, unsigned txnode)
{
    (void)ecb;
    (void)i;
    (void)txnode;
    return 0;
}
