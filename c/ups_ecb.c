/*
 * libups-ecb: the dispatcher (receiving and its checks, the life cycle, Hello and the recovery
 * window, the timers' entry, the blob) on top of ups_ecb_join.c, ups_ecb_bind.c and
 * ups_ecb_elect.c. SKELETON: to be completed by its owner.
 */
#include "ups_ecb_internal.h"

void ups_ecb_default_config(ups_ecb_config_t *cfg)
{
    cfg->bitrate = 500000u;
    cfg->fd = 0u;
    cfg->recovery_ms = 2000u;
    cfg->lease_s = 86400u;
    cfg->max_channels = UPS_ECB_CHANNELS;
    cfg->quota[0] = 1024u;
    for (unsigned c = 1u; c < 5u; c++) {
        cfg->quota[c] = 64u;
    }
}

int ups_ecb_init(ups_ecb_t *ecb, const ups_ecb_config_t *cfg, uint64_t instance)
{
    ups_ecb__copy((uint8_t *)ecb, NULL, (unsigned)sizeof(*ecb));
    if (cfg != NULL) {
        if (cfg->bitrate == 0u || cfg->recovery_ms < 100u || cfg->recovery_ms > 10000u) {
            return UPS_ERR_ARGUMENT;
        }
        ecb->cfg = *cfg;
    } else {
        ups_ecb_default_config(&ecb->cfg);
    }
    ups_ecb__put64(ecb->instance, instance);
    ups_ecb__join_init(ecb);
    ups_ecb__bind_init(ecb);
    return UPS_OK;
}

int ups_ecb_restore(ups_ecb_t *ecb, const uint8_t *blob, size_t size)
{
    (void)blob;
    (void)size;
    ups_ecb__count(&ecb->counters.blob_refused);
    return UPS_ERR_ARGUMENT;
}

static void hello(ups_ecb_t *ecb)
{
    ecb->recovering = 1u;
    ecb->t_recovery = ecb->now;
    ups_ecb__send_mgmt(ecb, 0x3300u, ups_ecb__get64(ecb->instance), 1);
}

void ups_ecb_start(ups_ecb_t *ecb, uint32_t now_ms)
{
    ecb->now = now_ms;
    ups_ecb__elect_start(ecb);
    hello(ecb);
}

void ups_ecb_rx(ups_ecb_t *ecb, uint32_t now_ms, const ups_frame_t *frame)
{
    ecb->now = now_ms;
    if ((frame->flags & (UPS_FRAME_RTR | UPS_FRAME_ERR)) != 0u ||
        (frame->flags & UPS_FRAME_EXT) == 0u) {
        ups_ecb__count(&ecb->counters.foreign);
        return;
    }
    /* SKELETON: the dispatch to the parts */
}

void ups_ecb_tick(ups_ecb_t *ecb, uint32_t now_ms)
{
    ecb->now = now_ms;
    if (ecb->recovering && ups_ecb__since(now_ms, ecb->t_recovery) >= ecb->cfg.recovery_ms) {
        ecb->recovering = 0u;
        ecb->started_up = 1u;
        ups_ecb__bind_recovered(ecb);
        ups_ecb__join_recovered(ecb);
    }
    ups_ecb__join_tick(ecb);
    ups_ecb__bind_tick(ecb);
    if (ups_ecb__elect_tick(ecb) & UPS_ECB__SAY_HELLO) {
        hello(ecb);
    }
}

const ups_frame_t *ups_ecb_tx_peek(const ups_ecb_t *ecb)
{
    return ecb->tx_count > 0u ? &ecb->tx[0] : NULL;
}

void ups_ecb_tx_pop(ups_ecb_t *ecb)
{
    if (ecb->tx_count == 0u) {
        return;
    }
    for (unsigned i = 1u; i < ecb->tx_count; i++) {
        ecb->tx[i - 1u] = ecb->tx[i];
    }
    ecb->tx_count--;
}

unsigned ups_ecb_notes(ups_ecb_t *ecb)
{
    unsigned notes = ecb->notes;
    ecb->notes = 0u;
    return notes;
}

size_t ups_ecb_save(const ups_ecb_t *ecb, uint8_t *out, size_t cap)
{
    (void)ecb;
    (void)out;
    (void)cap;
    return 0u;
}

int ups_ecb_role(const ups_ecb_t *ecb)
{
    return ecb->elect.role;
}

const ups_ecb_counters_t *ups_ecb_counters(const ups_ecb_t *ecb)
{
    return &ecb->counters;
}

int ups_ecb_node(const ups_ecb_t *ecb, int i, uint64_t *node_id)
{
    if (i < 0 || i >= UPS_ECB_NODES || ecb->join.nodes[i].txnode == 0xFFu) {
        return -1;
    }
    *node_id = ups_ecb__get64(ecb->join.nodes[i].node_id);
    return ecb->join.nodes[i].txnode;
}

int ups_ecb_channel(const ups_ecb_t *ecb, int i, uint64_t *uid)
{
    if (i < 0 || i >= UPS_ECB_CHANNELS || ecb->bind.channels[i].etag == 0u) {
        return -1;
    }
    *uid = ups_ecb__get64(ecb->bind.channels[i].uid);
    return ecb->bind.channels[i].etag;
}
