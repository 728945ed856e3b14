/*
 * What a host program (the Python binding in broker/c_ecb.py) needs to know of libups-ecb as it
 * was compiled: the size of ups_ecb_t and the configuration macros. Not for firmware.
 */
#include "../ups_ecb.h"

/** sizeof(ups_ecb_t), so that the caller can place one. */
size_t ups_ecb_host_size(void);
/** The configuration: 0 nodes, 1 channels, 2 streams, 3 queries, 4 TX depth, 5 held requests,
 *  6 watched requests, 7 bytes per counter, 8 UPS_ECB_BLOB_MAX, 9 UPS_MTU (the data bytes of
 *  ups_frame_t); else -1. */
long ups_ecb_host_config(int what);

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
    default: return -1;
    }
}
