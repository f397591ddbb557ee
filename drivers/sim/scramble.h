// A seed spread over all 64 bits (SplitMix64's finaliser): the sim's hand and
// walker seed their random streams from sim.seed and a tag of their own, so
// neighbouring seeds and the two operators draw unrelated numbers.
#pragma once

#include <cstdint>

namespace aggscan::sim {

inline uint64_t Scramble(uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31);
}

}  // namespace aggscan::sim
