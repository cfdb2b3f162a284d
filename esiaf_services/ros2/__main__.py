from esiaf_services.ros2.service import Ros2, main

raise SystemExit(main(Ros2))
