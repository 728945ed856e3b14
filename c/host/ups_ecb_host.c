/*
 * What a host program (the Python binding in broker/c_ecb.py) needs to know of libups-ecb as it
 * was compiled: the size of ups_ecb_t and the configuration macros. Not for firmware.
 */
#include "../ups_ecb_internal.h"

/** sizeof(ups_ecb_t), so that the caller can place one. */
size_t ups_ecb_host_size(void);
/** The configuration: 0 nodes, 1 channels, 2 streams, 3 queries, 4 TX depth, 5 held requests,
 *  6 watched requests, 7 bytes per counter, 8 UPS_ECB_BLOB_MAX, 9 UPS_MTU (the data bytes of
 *  ups_frame_t), 10 waiting Rosters; else -1. */
long ups_ecb_host_config(int what);
/** For tests only (tests/test_cecb_fuzz.py): the Rosters waiting, their node entries in
 *  @p slots (UPS_ECB_ROSTERS bytes), oldest first. */
unsigned ups_ecb_host_rosters(const ups_ecb_t *ecb, uint8_t *slots);
/** For tests only (tests/test_cecb_elect.py): the election alone, at @p now_ms. @p what: 0 its
 *  tick, 1 a CAN-ECB frame heard (Hello, Serving or Probe pass their data as the instance),
 *  2 a frame asked while standing by, 3 its start: the verdict (UPS_ECB__SAY_HELLO); 4: the
 *  ms until its next timer (ups_ecb__elect_next). */
unsigned ups_ecb_host_elect(ups_ecb_t *ecb, uint32_t now_ms, int what, uint32_t id,
                            const uint8_t *data, unsigned len, int busy);

size_t ups_ecb_host_size(void)
{
    return sizeof(ups_ecb_t);
}

long ups_ecb_host_config(int what)
{
    switch (what) {
    case 0: return UPS_ECB_NODES;
    case 1: return UPS_ECB_CHANNELS;
    case 2: return UPS_ECB_STREAMS;
    case 3: return UPS_ECB_QUERIES;
    case 4: return UPS_ECB_TX_DEPTH;
    case 5: return UPS_ECB_HELD;
    case 6: return UPS_ECB_WATCHED;
    case 7: return (long)sizeof(UPS_ECB_COUNTER_T);
    case 8: return (long)UPS_ECB_BLOB_MAX;
    case 9: return UPS_MTU;
    case 10: return UPS_ECB_ROSTERS;
    default: return -1;
    }
}

unsigned ups_ecb_host_rosters(const ups_ecb_t *ecb, uint8_t *slots)
{
    for (unsigned q = 0u; q < ecb->bind.r_waiting; q++) {
        slots[q] = ecb->bind.rosters[q].slot;
    }
    return ecb->bind.r_waiting;
}

unsigned ups_ecb_host_elect(ups_ecb_t *ecb, uint32_t now_ms, int what, uint32_t id,
                            const uint8_t *data, unsigned len, int busy)
{
    unsigned field = (unsigned)(id & UPS_ECB__ETAG_MASK);
    unsigned status = (field >> 8) & 0xFu;
    int claim = (id >> UPS_ECB__TXNODE_SHIFT) == UPS_ECB__MGMT && (field & 0xF0FFu) == 0x3000u &&
                (status == 0x3u || status == 0x6u || status == 0x9u) && len == 8u;
    ecb->now = now_ms;
    switch (what) {
    case 0: return ups_ecb__elect_tick(ecb);
    case 1: return ups_ecb__elect_heard(ecb, status, claim ? data : NULL, id, data, busy);
    case 2: return ups_ecb__elect_asked(ecb, id, data, len);
    case 3: ups_ecb__elect_start(ecb); return 0u;
    case 4: return ups_ecb__elect_next(ecb);
    default: return 0u;
    }
}
