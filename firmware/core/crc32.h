/* CRC-32/ISO-HDLC, the packet checksum of docs/daq-protocol.md (section 1).
 *
 * Polynomial 0x04C11DB7 reflected (0xEDB88320), init 0xFFFFFFFF, input and output reflected,
 * xor-out 0xFFFFFFFF: the zlib/Ethernet CRC.  Check value: crc32("123456789") = 0xCBF43926.
 * Table-driven (one 1 KiB constant table, in flash on a microcontroller).  A hardware CRC unit may
 * replace it only if it passes the check value: STM32's CRC unit computes CRC-32/MPEG-2 by default
 * (no reflection, no xor-out; 0x0376E6E7 for the same string), see firmware/README.md.
 */
#ifndef BRIDGE_CRC32_H
#define BRIDGE_CRC32_H

#include <stddef.h>
#include <stdint.h>

#define CRC32_INIT 0xFFFFFFFFu
#define CRC32_CHECK 0xCBF43926u /* crc32("123456789") */

/* Continue a CRC over `n` bytes: start with CRC32_INIT, finish with crc32_final(). */
uint32_t crc32_update(uint32_t state, const uint8_t *data, size_t n);

/* The finished CRC of a running state (the xor-out). */
uint32_t crc32_final(uint32_t state);

/* The CRC-32 of `n` bytes in one call. */
uint32_t crc32(const uint8_t *data, size_t n);

#endif
