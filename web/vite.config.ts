import { defineConfig } from "vitest/config";

// `npm run dev` proxies the API to a running `isovox serve`, so the page can be developed with
// hot reloading against real data.
const api = process.env.ISOVOX_URL ?? "http://127.0.0.1:7070";

export default defineConfig({
  base: "/",
  build: {
    target: "es2022",
    // three.js alone is about 700 kB minified; one chunk keeps the first load at two requests.
    chunkSizeWarningLimit: 1024,
    sourcemap: false,
  },
  server: {
    proxy: { "/v1": api, "/healthz": api },
  },
  test: {
    include: ["test/**/*.test.ts"],
    environment: "node",
  },
});
