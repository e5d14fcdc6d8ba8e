/* Drives fuzz_core.c's LLVMFuzzerTestOneInput without libFuzzer (gcc): pseudo-random inputs of 0 to
 * 4096 bytes from a fixed seed, so a run is reproducible. tests/native/test_c_core.py builds it under
 * AddressSanitizer and UndefinedBehaviorSanitizer; any report or abort fails the test.
 *
 *   gcc -std=c99 -g -O1 -fsanitize=address,undefined -fno-sanitize-recover=all -I runtime/native \
 *       runtime/native/fuzz/replay.c runtime/native/fuzz/fuzz_core.c runtime/native/dimenet_*.c -lm
 *   ./a.out 20000 1    (cases, seed) */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

static uint64_t next(uint64_t *state) /* xorshift64* */
{
    uint64_t x = *state;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    *state = x;
    return x * 2685821657736338717ull;
}

int main(int argc, char **argv)
{
    static uint8_t buffer[4096];
    long cases = argc > 1 ? atol(argv[1]) : 10000, c;
    uint64_t state = 0x9E3779B97F4A7C15ull ^ (uint64_t)(argc > 2 ? atol(argv[2]) : 1);
    for (c = 0; c < cases; c++) {
        size_t size = (size_t)(next(&state) % (sizeof buffer + 1)), i;
        for (i = 0; i < size; i++) {
            buffer[i] = (uint8_t)(next(&state) >> 56);
        }
        LLVMFuzzerTestOneInput(buffer, size);
    }
    printf("replay: %ld cases\n", cases);
    return 0;
}
