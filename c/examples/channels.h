/* The examples' channels, made with: ups uid robot/speed robot/cmd */
#define UPS_UID_ROBOT_SPEED 0xeb79dab9bbb48dc7ULL /* robot/speed */
#define UPS_UID_ROBOT_CMD 0x30347af5aa2b0b72ULL /* robot/cmd */
