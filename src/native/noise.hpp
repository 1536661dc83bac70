// noise.NormalStream in C++: standard normal draws by the 256-layer ziggurat on numpy's SFC64 outputs, each step
// as multibody_sim/noise.py (the specification) writes it, so that both give the same numbers bit for bit: integer
// masks and shifts, one rounded product per fast draw, std::log and std::exp (libm's, as Python's math module) on
// the slow paths. The tables come from Python (noise.native_tables()).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <vector>

namespace multibody_sim
{
  // noise._tables(): per layer its width · 2⁻⁵³, the 53-bit bound inside the next layer's edge, the density at the
  // edges and its rise to the next edge; the rightmost edge R
  struct ZigguratTables
  {
    std::vector<double> width;     // (256,) W
    std::vector<uint64_t> inside;  // (256,) K
    std::vector<double> density;   // (257,) F
    std::vector<double> rise;      // (256,) D
    double edge = 0.0;             // R
  };

  // numpy's SFC64 (its state: three words and a counter, numpy.random.SFC64().state["state"]["state"])
  struct Sfc64
  {
    uint64_t * s;

    uint64_t next()
    {
      const uint64_t out = s[0] + s[1] + s[3];
      s[3] += 1;
      s[0] = s[1] ^ (s[1] >> 11);
      s[1] = s[2] + (s[2] << 3);
      s[2] = ((s[2] << 24) | (s[2] >> 40)) + out;
      return out;
    }
  };

  // One draw (noise.py's module docstring; fill_python and _slow there)
  inline double standard_normal(Sfc64 & bits, const ZigguratTables & z)
  {
    constexpr double scale = 1.0 / 9007199254740992.0;  // 2⁻⁵³
    for (;;)
    {
      const uint64_t r = bits.next();
      const size_t layer = static_cast<size_t>(r & 255);
      const uint64_t sign = (r >> 8 & 1) << 63;  // the sign bit: x negated without a branch (half the draws)
      const bool negative = sign != 0;
      const uint64_t u = r >> 11;
      // u < 2⁵³ converts exactly through int64 (one instruction; uint64's conversion takes a branch)
      const double magnitude = static_cast<double>(static_cast<int64_t>(u)) * z.width[layer];
      uint64_t word;
      std::memcpy(&word, &magnitude, sizeof word);
      word ^= sign;
      double x;
      std::memcpy(&x, &word, sizeof x);
      if (u < z.inside[layer])
        return x;
      if (layer == 0)  // the tail beyond R
        for (;;)
        {
          const double a = -std::log(static_cast<double>((bits.next() >> 11) + 1) * scale) / z.edge;
          const double b = -std::log(static_cast<double>((bits.next() >> 11) + 1) * scale);
          if (b + b > a * a)
            return negative ? -(z.edge + a) : z.edge + a;
        }
      const double U = static_cast<double>(bits.next() >> 11) * scale;
      if (z.density[layer] + U * z.rise[layer] < std::exp(-0.5 * (x * x)))
        return x;
    }
  }

  // NormalStream.fill: the next n draws of the stream at `state` (4 words, advanced) into out
  inline void fill_normals(uint64_t * state, double * out, size_t n, const ZigguratTables & z)
  {
    uint64_t words[4] = {state[0], state[1], state[2], state[3]};  // (kept in registers, written back once)
    Sfc64 bits{words};
    for (size_t i = 0; i < n; ++i)
      out[i] = standard_normal(bits, z);
    std::copy(words, words + 4, state);
  }
} // namespace multibody_sim
